"""GRaF's neighbor-feature components (graf.models.graf.features): each mode on its own, chosen by the Hydra
group ``model/features``, recorded as a plain dict in the checkpoint; checkpoints written before the
components (the mode as the string hyperparameter ``neighbour_features`` / ``neighbor_features``, the mode's
parameters at the top of the state dict) load with strict key matching and predict the same."""

from __future__ import annotations

from pathlib import Path

import lightning
import pytest
import torch
from hydra.utils import instantiate

from graf.models.base import CheckpointError, check_checkpoint, read_checkpoint
from graf.models.graf import GRaFModule
from graf.models.graf.features import (
    MODES,
    PAPER_MODE,
    PooledFeatures,
    RayFeatures,
    RayKNNFeatures,
    RayWeightsFeatures,
)
from graf.models.knn import KNNModule
from graf.run.evaluate import checkpoint_model_choice, load_checkpoint_model
from tests.models.test_ray_features import TINY, synthetic_batch

PUBLISHED = Path(__file__).resolve().parents[2] / "sweeps" / "learning_curves" / "rfid_sparse"
# the parameters in the order the model registered them before the components (the output head last)
OLD_ORDER = (
    "encoder.",
    "mlp1.",
    "ray_proj.",
    "ray_tokens.",
    "query_voxel.",
    "query_direction.",
    "query_target.",
    "scene_blocks.",
    "mlp2.",
    "voxel_distance.",
    "ray_blocks.",
    "head.",
    "weight_query.",
)


def _model(features, **kw) -> GRaFModule:
    torch.manual_seed(0)
    return GRaFModule(**TINY, features=features, **kw)


def _context(model: GRaFModule, batch: dict, pix: torch.Tensor) -> tuple:
    """The component's inputs for the rays at ``pix`` of item 0 (and item 1): ``(ctx, q, bi, pix)``."""
    ctx = model.prepare(batch)
    bi = torch.tensor([0] * len(pix) + [1] * len(pix))
    pix = torch.cat([pix, pix])
    q = torch.randn(len(pix), 3, model.d_model)
    return ctx, q, bi, pix


# ---------------------------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "overrides,cls,method",
    [
        (("model=graf_cpu",), PooledFeatures, "graf"),
        (("model=graf_cpu", "model/features=ray"), RayFeatures, "graf-ray"),
        (("model=graf_cpu", "model/features=ray_knn"), RayKNNFeatures, "graf-ray-knn"),
        (("model=graf_cpu", "model/features=ray_weights"), RayWeightsFeatures, "graf-ray-weights"),
        (("model=graf_cpu_ray_weights",), RayWeightsFeatures, "graf-ray-weights"),
        (
            ("model=graf_cpu_ray_weights", "model/features=ray", "model.features.pixel_window=0"),
            RayFeatures,
            "graf-ray",
        ),
        (("model=graf_cpu", "model.residual=true", "model/features=ray"), RayFeatures, "graf-residual-ray"),
    ],
)
def test_the_features_group_chooses_the_component(compose_cfg, overrides, cls, method):
    cfg = compose_cfg("train", overrides).model
    assert cfg.features._target_ == f"graf.models.graf.features.{cls.__name__}"
    model = instantiate(cfg, encoder_widths=[4, 8, 8, 8], max_samples=4)
    assert type(model.features) is cls and model.method == method
    saved = model.hparams.features
    assert type(saved) is dict and saved == dict(cfg.features)  # plain, serialisable, what was composed
    if "model.features.pixel_window=0" in overrides:
        assert model.features.pixel_window == 0 and saved["pixel_window"] == 0


def test_the_paper_mode_has_one_home(compose_cfg):
    """conf/model/graf.yaml's default mode is :data:`PAPER_MODE`, the constructor's default and the legacy mode."""
    import inspect

    cfg = compose_cfg("train", ("model=graf",)).model
    assert cfg.features._target_ == MODES[PAPER_MODE]
    assert inspect.signature(GRaFModule.__init__).parameters["features"].default == PAPER_MODE


def test_a_component_config_is_checked():
    with pytest.raises(ValueError, match="not a NeighborFeatures component"):
        _model({"_target_": "torch.nn.Linear"})
    with pytest.raises(ValueError, match="ray_feature_dim must be >= 1"):
        _model({"_target_": MODES["ray"], "ray_feature_dim": 0})
    with pytest.raises(TypeError, match="unexpected keyword argument"):
        _model({"_target_": MODES["pooled"], "pixel_window": 1})  # pooled has no pixel window
    with pytest.raises(TypeError, match="unexpected keyword argument"):
        GRaFModule(**TINY, neighbour_features_typo="ray")


# ---------------------------------------------------------------------------------------------- components
def test_pooled_makes_one_token_per_neighbor_and_one_query_axis_per_item():
    model = _model("pooled").eval()
    batch = synthetic_batch()
    with torch.no_grad():
        ctx, q, bi, pix = _context(model, batch, torch.tensor([0, 500, 32399]))
        assert ctx["tokens"].shape == (2, 3, model.d_model) and torch.equal(ctx["tokens"][1, 2], torch.zeros(8))
        x, tokens, key_mask, _ = model.features.scene_inputs(ctx, q[:3], bi[:3], pix[:3], one_item=True)
        assert x.shape == (1, 9, model.d_model) and tokens.shape == (1, 3, model.d_model) and key_mask.shape == (1, 3)
        x, tokens, key_mask, _ = model.features.scene_inputs(ctx, q, bi, pix, one_item=False)
        assert x.shape == q.shape and tokens.shape == (6, 3, model.d_model) and not key_mask[3:, 2].any()
        assert model.features.output(torch.randn(6, model.d_model), {}).shape == (6, 2)
    assert not hasattr(model, "mlp1") and not hasattr(model, "head")  # the component owns them


def test_ray_reads_each_neighbor_at_the_rays_pixel():
    model = _model({"_target_": MODES["ray"], "pixel_window": 1}).eval()
    batch = synthetic_batch()
    rows, cols = torch.tensor([10, 0]), torch.tensor([20, 359])
    with torch.no_grad():
        ctx, q, bi, pix = _context(model, batch, rows * 360 + cols)
        x, tokens, key_mask, ray = model.features.scene_inputs(ctx, q, bi, pix, one_item=False)
    assert torch.equal(x, q) and tokens.shape == (4, 3, model.d_model) and ray["window"].shape == (4, 3, 9)
    for i, (b, p) in enumerate(zip(bi.tolist(), pix.tolist())):
        expect = batch["src_spectra"][b, :, p // 360, p % 360] * batch["src_mask"][b]  # padded neighbors read 0
        assert torch.equal(ray["window"][i, :, 4], expect)


@pytest.mark.parametrize("features", ["ray_knn", "ray_weights"])
def test_knn_based_components_start_as_idw_at_every_ray(features):
    model = _model(features).eval()
    batch = synthetic_batch()
    with torch.no_grad():
        ctx, q, bi, pix = _context(model, batch, torch.tensor([3, 777, 32000]))
        _, _, _, ray = model.features.scene_inputs(ctx, q, bi, pix, one_item=False)
        out = model.features.output(torch.randn(len(pix), model.d_model), ray)  # any state: no correction at init
    knn = KNNModule(weighting="idw").predict_spectra(batch).flatten(1)[bi, pix]
    assert torch.allclose(out[:, 0], knn, atol=1e-6) and torch.equal(out[:, 1], torch.zeros(len(pix)))
    assert hasattr(model.features, "head") == (features == "ray_knn")
    assert hasattr(model.features, "weight_query") == (features == "ray_weights")


@pytest.mark.parametrize("features", ["pooled", "ray"])
def test_residual_is_an_option_of_pooled_and_ray_that_zeroes_their_head(features):
    plain, residual = _model(features), _model(features, residual=True)
    assert plain.features.head.weight.abs().sum() > 0 and residual.features.head.weight.abs().sum() == 0
    assert type(plain.base).__name__ == "NoBase" and residual.base.weighting == "idw"


# ---------------------------------------------------------------------------------------------- old checkpoints
def _old_checkpoint(model: GRaFModule, mode: str, spelling: str) -> dict:
    """A checkpoint as GRaF wrote it before the components: the mode a string hyperparameter beside the ray
    settings, the component's parameters at the top of the state dict."""
    hp = {k: v for k, v in dict(model.hparams).items() if k != "features"}
    hp.update({spelling: mode, "ray_feature_dim": 8, "pixel_window": 1})
    state = {k.removeprefix("features."): v for k, v in model.state_dict().items()}
    return {
        "state_dict": state,
        "hyper_parameters": hp,
        "hparams_name": "kwargs",
        "pytorch-lightning_version": lightning.__version__,
        "graf": {"target": "graf.models.graf.module.GRaFModule", "layout": GRaFModule.LAYOUT},
    }


@pytest.mark.parametrize(
    "mode,residual,spelling",
    [
        ("pooled", False, "neighbour_features"),
        ("ray", False, "neighbor_features"),
        ("ray_knn", False, "neighbour_features"),
        ("ray_weights", False, "neighbour_features"),
        ("pooled", True, "neighbor_features"),
        ("ray", True, "neighbour_features"),
    ],
)
@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_an_old_format_checkpoint_loads_strictly_and_predicts_the_same(tmp_path, mode, residual, spelling):
    model = _model(mode, residual=residual)
    with torch.no_grad():
        for p in model.parameters():  # every parameter matters (zero-initialised heads too)
            p.add_(0.05 * torch.randn_like(p))
    old = _old_checkpoint(model, mode, spelling)
    assert any(k.startswith(("mlp1.", "ray_proj.")) for k in old["state_dict"])
    torch.save(old, tmp_path / "old.ckpt")
    with pytest.warns(FutureWarning, match="deprecated"):
        loaded = GRaFModule.load_from_checkpoint(tmp_path / "old.ckpt", map_location="cpu", strict=True)
    assert loaded.method == model.method and dict(loaded.hparams) == dict(model.hparams)
    with pytest.warns(FutureWarning):  # what a resumed run compares with its own settings (graf.run.resume)
        assert GRaFModule.upgrade_hparams(old["hyper_parameters"]) == dict(model.hparams)
    fresh = _model(mode, residual=residual)
    fresh.load_state_dict(old["state_dict"], strict=True)  # fine-tuning's (finetune.init_from) of the old keys
    batch = synthetic_batch()
    with torch.no_grad():
        expect = model.eval().predict_spectra(batch)
        assert torch.equal(loaded.eval().predict_spectra(batch), expect)
        assert torch.equal(fresh.eval().predict_spectra(batch), expect)


def test_an_old_optimiser_state_is_put_in_the_new_order_of_the_parameters():
    model = _model("ray_weights")
    opt = model.configure_optimizers()["optimizer"]
    model.render(model.prepare(synthetic_batch()), torch.randint(0, 32400, (2, 16))).sum().backward()
    opt.step()
    names = [n for n, _ in model.named_parameters()]
    old_names = sorted(
        names,
        key=lambda n: OLD_ORDER.index(next(p for p in OLD_ORDER if n.removeprefix("features.").startswith(p))),
    )
    assert old_names != names  # weight_query was registered last
    state = opt.state_dict()
    old = _old_checkpoint(model, "ray_weights", "neighbor_features")
    old["optimizer_states"] = [{**state, "state": {old_names.index(n): state["state"][i] for i, n in enumerate(names)}}]
    model.on_load_checkpoint(old)
    assert old["optimizer_states"][0]["state"].keys() == state["state"].keys()
    for i in state["state"]:
        assert torch.equal(old["optimizer_states"][0]["state"][i]["exp_avg"], state["state"][i]["exp_avg"])


@pytest.mark.parametrize("mode,method", [("ray_weights", "graf-ray-weights"), ("pooled", "graf")])
def test_published_checkpoints_load_and_predict(mode, method):
    """The learning curves' checkpoints (written with ``neighbour_features``): strict keys, the same method
    name the published tables key on, finite spectra, and Adam's moments in their parameters' shapes."""
    path = PUBLISHED / mode / "step_10000" / "checkpoints" / "last.ckpt"
    ckpt = read_checkpoint(path)
    assert ckpt["hyper_parameters"]["neighbour_features"] == mode
    check_checkpoint(ckpt, GRaFModule, path)
    with pytest.warns(FutureWarning, match="deprecated"):
        model = GRaFModule.load_from_checkpoint(path, map_location="cpu", strict=True).eval()
    assert model.method == method and model.hparams.features["_target_"] == MODES[mode]
    with torch.no_grad():
        pred = model.predict_spectra(synthetic_batch(B=1))
    assert pred.shape == (1, 90, 360) and torch.isfinite(pred).all() and pred.std() > 0
    model.on_load_checkpoint(ckpt)
    params = list(model.parameters())
    for i, s in ckpt["optimizer_states"][0]["state"].items():
        assert s["exp_avg"].shape == params[i].shape


def test_graf_eval_refuses_another_features_choice_for_a_checkpoint(compose_cfg):
    """``model/features=X`` on a trained checkpoint describes a model that did not run: refused unless it is
    the checkpoint's own (also for a checkpoint written before model/features)."""
    path = PUBLISHED / "ray_weights" / "step_10000" / "checkpoints" / "last.ckpt"
    assert checkpoint_model_choice([f"ckpt_path={path}", "model/features=ray"]) == "graf"
    cfg = compose_cfg("eval", ("model=graf_cpu", "model/features=ray", f"ckpt_path={path}"))
    with pytest.warns(FutureWarning), pytest.raises(CheckpointError, match="model.features=.*RayFeatures"):
        load_checkpoint_model(cfg, str(path), ["model/features=ray"])
    cfg = compose_cfg("eval", ("model=graf_cpu", "model/features=ray_weights", f"ckpt_path={path}"))
    with pytest.warns(FutureWarning):
        model, ran, _ = load_checkpoint_model(cfg, str(path), ["model/features=ray_weights"])
    assert model.method == "graf-ray-weights" and ran.features._target_ == MODES["ray_weights"]


def test_a_seed_draws_the_model_weights_whatever_the_output_of_the_mode():
    """The component's output parameters (``head``, ``weight_query``) are drawn last, as in the model before the
    components: ``ray`` and ``ray_weights`` differ only there, so with one seed every other weight is equal (the
    main job's seed gives the weights, and so the figures, it gave before the components)."""
    GRaFModule(**TINY, features="ray")  # the first model built in a process draws once more (a lazy set-up)
    torch.manual_seed(0)
    ray = GRaFModule(**TINY, features="ray").state_dict()
    torch.manual_seed(0)
    ray_weights = GRaFModule(**TINY, features="ray_weights").state_dict()
    shared = sorted(set(ray) & set(ray_weights))
    assert len(shared) > 20 and any(k.startswith("features.ray_tokens.") for k in shared)
    assert [k for k in shared if not torch.equal(ray[k], ray_weights[k])] == []
    assert set(ray) - set(ray_weights) == {"features.head.weight", "features.head.bias"}
