"""GRaF model (graf.models.graf): contracts, invariances and short CPU training runs on real batches."""

from __future__ import annotations

import functools
import inspect
import math

import lightning as L
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from graf.app.config import CONF_DIR
from graf.bands import Band
from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector
from graf.data.scenes import NeRF2Scene
from graf.geometry.rays import num_samples, random_pixels
from graf.models.graf import CrossAttentionBlock, GRaFModule, ResNetEncoder, SelfAttentionBlock
from graf.models.knn import KNNModule

UHF = Band(name="915mhz", frequency_hz=915e6)


def _datamodule(path, L=3, L_train=(1, 3), batch_size=2, band=UHF) -> SpectrumDataModule:
    dm = SpectrumDataModule(
        NeRF2Scene(name="tiny", path=str(path)),
        band,
        NeighborSelector(L=L, L_train=L_train, radius=10.0),
        batch_size=batch_size,
    )
    dm.setup()
    return dm


def _eval_batch(dm, n=2) -> dict:
    return next(iter(dm.test_dataloader())) if n == dm.batch_size else dm.eval_batch(list(range(n)))


@functools.cache
def _composed(name: str, overrides: tuple[str, ...]) -> dict:
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR / "model"), version_base="1.3"):
        cfg = compose(config_name=name, overrides=list(overrides))
    GlobalHydra.instance().clear()
    return OmegaConf.to_container(cfg)


def preset_config(name: str, *overrides: str) -> DictConfig:
    """conf/model/<name>.yaml as ``model=<name>`` composes it (its defaults list: graf.yaml, the features
    group); ``overrides`` in the model's own terms, e.g. ``features=ray``."""
    return OmegaConf.create(_composed(name, overrides))


def _preset(name: str, *group_overrides: str, **overrides) -> GRaFModule:
    """The model exactly as conf/model/<name>.yaml builds it (with overrides)."""
    cfg = preset_config(name, *group_overrides)
    torch.manual_seed(0)
    return instantiate(cfg, **overrides)


def _small(**overrides) -> GRaFModule:
    """The CPU preset with few voxels per ray: the real architecture, fast inference."""
    return _preset("graf_cpu", **{"max_samples": 4, "chunk_rays": 40000, **overrides}).eval()


@pytest.fixture
def tiny(make_scene):
    return _datamodule(make_scene(n=16))


@pytest.fixture(scope="module")
def rfid():
    return _datamodule("embedded:rfid_s23_200", L=10, L_train=(3, 10), batch_size=2)


# ---------------------------------------------------------------------------------------------- configs
def test_preset_configs_are_the_constructor_arguments(compose_cfg):
    signature = inspect.signature(GRaFModule.__init__).parameters
    params = {k for k, p in signature.items() if p.kind != p.VAR_KEYWORD} - {"self"}  # **legacy: old checkpoints
    for name, method in (("graf", "graf"), ("graf_cpu", "graf")):
        cfg = compose_cfg("train", (f"model={name}",)).model
        assert set(cfg) - {"_target_", "_recursive_"} == params
        model = instantiate(cfg)
        assert model.method == method and model.has_trainable_parameters
        assert model.hparams.encoder_widths == list(cfg.encoder_widths)
    paper, cpu = compose_cfg("train", ("model=graf",)).model, compose_cfg("train", ("model=graf_cpu",)).model
    assert list(paper.encoder_widths) == [64, 128, 256, 512] and paper.rays_per_step == 5120
    assert (paper.d_model, paper.ray_heads, paper.ray_head_dim, paper.pe_freqs) == (16, 10, 8, 10)
    assert cpu.encoder_downsample == 2 and cpu.max_samples < paper.max_samples
    assert instantiate(compose_cfg("train", ("model=graf", "model.residual=true")).model).method == "graf-residual"


# ---------------------------------------------------------------------------------------------- parts


def test_encoder_is_resnet18_and_per_spectrum():
    enc = ResNetEncoder((64, 128, 256, 512))
    n_conv = sum(isinstance(m, torch.nn.Conv2d) and m.kernel_size != (1, 1) for m in enc.modules())
    assert n_conv == 17  # stem + 4 stages x 2 BasicBlocks x 2 convs (+ 3 shortcut 1x1 convs)
    assert 11.0e6 < sum(p.numel() for p in enc.parameters()) < 11.3e6  # ResNet-18 without its fc
    small = ResNetEncoder((16, 32, 64, 128), downsample=2).eval()
    x = torch.rand(3, 1, 90, 360)
    with torch.no_grad():
        f = small(x)
        assert f.shape == (3, 128) and torch.isfinite(f).all()
        assert torch.allclose(small(x[1:2]), f[1:2], atol=1e-5)  # GroupNorm: no batch effects


def test_attention_blocks_mask_and_sizes():
    torch.manual_seed(0)
    cross, selfb = CrossAttentionBlock(16, 1, 16), SelfAttentionBlock(16, 10, 8)
    assert cross.attn.q.weight.shape == (16, 16) and selfb.attn.q.weight.shape == (80, 16)
    q, ctx = torch.randn(2, 5, 16), torch.randn(2, 4, 16)
    mask = torch.tensor([[True, True, False, False], [True, True, True, True]])
    out = cross(q, ctx, mask)
    garbage = ctx.clone()
    garbage[0, 2:] = 1e3
    assert torch.allclose(cross(q, garbage, mask), out, atol=1e-6)
    assert torch.allclose(cross(q[:1], ctx[:1, :2]), out[:1], atol=1e-6)
    y = selfb(q)
    assert y.shape == q.shape and torch.allclose(y.mean(-1), torch.zeros(2, 5), atol=1e-5)  # post-norm output


def test_voxels_follow_the_scene_and_band(rfid):
    b = _eval_batch(rfid)
    assert num_samples(torch.tensor([5.56]), torch.tensor([0.328]), 128) == [17]
    assert num_samples(b["ray_length"], b["wavelength"], 128) == [17, 17]  # rfid_s23 at 915 MHz
    assert num_samples(torch.tensor([5.56]), torch.tensor([0.0125]), 128) == [128]  # capped
    assert num_samples(torch.tensor([5.56, 5.56]), torch.tensor([0.328, 0.125]), 32) == [17, 32]
    step = float(b["ray_length"][0]) / 17
    assert abs(step - float(b["wavelength"][0])) < 0.02  # voxel size ~ the wavelength


def test_items_with_different_voxel_counts_share_a_batch(tiny):
    model = _small(max_samples=32)
    b = _eval_batch(tiny)
    b["wavelength"] = b["wavelength"] * torch.tensor([1.0, 0.5])  # item 1: twice the voxels
    pix = torch.arange(0, 32400, 97).expand(2, -1)
    with torch.no_grad():
        ctx = model.prepare(b)
        s0, s1 = model.samples_per_ray(b)
        assert s1 > s0 and model.mean_samples_per_ray(b)[1] > model.mean_samples_per_ray(b)[0]
        both = model.render(ctx, pix)
        for i in range(2):
            one = model.render(model.prepare({k: v[i : i + 1] for k, v in b.items()}), pix[i : i + 1])
            assert torch.allclose(both[i], one[0], atol=1e-5)


# ---------------------------------------------------------------------------------------------- inference
@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_prediction_contract_and_invariances(tiny):
    model = _small()
    b = _eval_batch(tiny)
    assert b["src_mask"].all() and b["src_pos"].shape[1] == 3
    with torch.no_grad():
        pred = model.predict_spectra(b)
        assert pred.shape == (2, 90, 360) and pred.dtype == torch.float32
        assert torch.isfinite(pred).all() and (pred >= 0).all() and pred.std() > 0

        # a padded neighbor (mask False) holding garbage changes nothing
        g = dict(b)
        g["src_pos"] = torch.cat([b["src_pos"], torch.full((2, 1, 3), 1e4)], 1)
        g["src_spectra"] = torch.cat([b["src_spectra"], torch.rand(2, 1, 90, 360) * 100], 1)
        g["src_mask"] = torch.cat([b["src_mask"], torch.zeros(2, 1, dtype=torch.bool)], 1)
        assert torch.allclose(model.predict_spectra(g), pred, atol=1e-5)

        # L = 1, a co-located neighbor, all-zero and all-one spectra
        one = {
            **b,
            "src_pos": b["src_pos"][:, :1],
            "src_spectra": b["src_spectra"][:, :1],
            "src_mask": b["src_mask"][:, :1],
        }
        p1 = model.predict_spectra(one)
        assert p1.shape == (2, 90, 360) and torch.isfinite(p1).all() and not torch.allclose(p1, pred)
        co = {**b, "src_pos": b["src_pos"].clone()}
        co["src_pos"][:, 0] = b["tgt_pos"]
        assert torch.isfinite(model.predict_spectra(co)).all()
        for value in (0.0, 1.0):
            flat = {**b, "src_spectra": torch.full_like(b["src_spectra"], value)}
            assert torch.isfinite(model.predict_spectra(flat)).all()

        # bf16 autocast on CPU: finite, and close to fp32 (geometry and PE stay fp32)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            pb = model.predict_spectra(b)
        assert pb.dtype == torch.float32 and torch.isfinite(pb).all()
        assert (pb - pred).abs().mean() < 0.02


def test_scene_index_enters_the_encoding(tiny):
    model = _small(use_scene_index=True)
    assert model.features.mlp1[0].in_features == 128 + 84 + 63 and model.query_voxel.in_features == 84
    b = _eval_batch(tiny)
    pix = torch.arange(0, 32400, 101).expand(2, -1)
    with torch.no_grad():
        p0 = model.render(model.prepare(b), pix)
        p1 = model.render(model.prepare({**b, "scene_index": torch.ones(2, dtype=torch.long)}), pix)
    assert torch.isfinite(p1).all() and not torch.allclose(p0, p1)


@pytest.mark.parametrize("weighting", ["idw", "barycentric"])
def test_residual_at_init_is_knn(rfid, weighting):
    model = _small(residual=True, weighting=weighting)
    assert model.method == "graf-residual"
    b = _eval_batch(rfid)
    with torch.no_grad():
        pred = model.predict_spectra(b)
    knn = KNNModule(weighting=weighting).predict_spectra(b)
    assert (pred - knn).abs().max() < 1e-5


def test_chunking_and_encoder_calls(rfid):
    model = _small(chunk_rays=1000)
    b = _eval_batch(rfid)
    b["src_mask"][0, 7:] = False  # fewer real neighbors for one target
    seen = []
    model.encoder.register_forward_hook(lambda mod, inp, out: seen.append(inp[0].shape[0]))
    with torch.no_grad():
        chunked = model.predict_spectra(b)
        assert seen == [int(b["src_mask"].sum())] == [17]  # once per real neighbor spectrum, not per ray
        model.chunk_rays = 40000
        whole = model.predict_spectra(b)
        assert seen == [17]  # evaluation: a spectrum already encoded with these weights is not encoded again
        model.encoder.stem[0].weight[0].add_(0.5)  # weights changed in place (as an optimiser step does)
        changed = model.predict_spectra(b)
        assert seen == [17, 17] and not torch.allclose(changed, whole)
        model.encoder.stem[0].weight[0].sub_(0.5)
    assert torch.allclose(chunked, whole, atol=1e-5)
    # training: one encoder pass per batch too, and rays_per_step split evenly across the targets
    model.train()
    pix = random_pixels(2, model.rays_per_step, model.global_step, "cpu")
    assert pix.shape == (2, 512) and all(len(set(r.tolist())) == 512 for r in pix)
    assert torch.equal(
        pix, random_pixels(2, model.rays_per_step, model.global_step, "cpu")
    )  # seeded from the global step
    seen.clear()
    model.render(model.prepare(b), pix).sum().backward()
    assert seen == [17]


# ---------------------------------------------------------------------------------------------- training
def test_optimisation_lowers_the_loss_on_a_fixed_batch(tiny):
    model = _preset("graf_cpu", max_samples=8)
    b = next(iter(tiny.train_dataloader()))
    pix = random_pixels(2, model.rays_per_step, model.global_step, "cpu")
    target = b["tgt_spectrum"].flatten(1).gather(1, pix)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(12):
        loss = torch.nn.functional.mse_loss(model.render(model.prepare(b), pix), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses) and losses[-1] < 0.5 * losses[0]


def test_learning_rate_schedule():
    model = _small(lr=1e-3, lr_decay=0.1, decay_steps=100)
    conf = model.configure_optimizers()
    opt, sched = conf["optimizer"], conf["lr_scheduler"]
    assert isinstance(opt, torch.optim.Adam) and sched["interval"] == "step"
    for _ in range(100):
        opt.step()
        sched["scheduler"].step()
    assert abs(opt.param_groups[0]["lr"] - 1e-4) < 1e-9


@pytest.mark.parametrize(
    "preset,overrides",
    [
        ("graf", {"rays_per_step": 128}),  # the paper's sizes, few rays per step to stay fast
        ("graf_cpu", {}),
        ("graf_cpu", {"residual": True, "weighting": "idw"}),
    ],
)
def test_two_training_steps_and_checkpoint(tiny, tmp_path, preset, overrides):
    model = _preset(preset, **overrides)
    before = {k: v.detach().clone() for k, v in model.named_parameters()}
    trainer = L.Trainer(
        max_steps=2,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        limit_val_batches=0,
        num_sanity_val_steps=0,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(model, datamodule=tiny)
    assert trainer.global_step == 2
    assert math.isfinite(float(trainer.callback_metrics["train/loss"]))
    changed = [k for k, v in model.named_parameters() if not torch.equal(v, before[k])]
    assert "features.head.weight" in changed and any(k.startswith("encoder.") for k in changed)
    assert any(k.startswith("features.mlp1.") for k in changed) and any(k.startswith("ray_blocks.") for k in changed)
    if preset == "graf_cpu":  # checkpoint round trip (hparams included) gives identical predictions
        path = tmp_path / "graf.ckpt"
        trainer.save_checkpoint(path)
        loaded = GRaFModule.load_from_checkpoint(path, map_location="cpu").eval()
        assert loaded.hparams == model.hparams and loaded.method == model.method
        model.eval()
        b = _eval_batch(tiny)
        with torch.no_grad():
            assert torch.equal(loaded.predict_spectra(b), model.predict_spectra(b))


def _rigid(b: dict, R: torch.Tensor, t: torch.Tensor) -> dict:
    """The batch with the whole scene (gateway, transmitters, box) moved by x -> R x + t."""
    move = lambda p: p @ R.T + t  # noqa: E731
    lo, hi = move(b["bounds"][:, 0]), move(b["bounds"][:, 1])
    return {
        **b,
        "tgt_pos": move(b["tgt_pos"]),
        "src_pos": move(b["src_pos"]),
        "gw_pos": move(b["gw_pos"]),
        "gw_rot": R @ b["gw_rot"],
        "bounds": torch.stack([torch.minimum(lo, hi), torch.maximum(lo, hi)], 1),
    }


def test_geometry_is_the_gateway_frame_in_metres(tiny):
    """Positions are metres in the gateway frame: moving or turning the whole scene (its box with it: a
    quarter turn keeps an axis-aligned box axis-aligned) changes nothing; scaling the scene, or another box
    (each ray's voxels end where it leaves the box), changes the prediction."""
    model = _small()
    b = _eval_batch(tiny)
    pix = torch.arange(0, 32400, 97).expand(2, -1)
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    with torch.no_grad():
        p0 = model.render(model.prepare(b), pix)
        moved = model.render(model.prepare(_rigid(b, R, torch.tensor([40.0, -7.0, 3.0]))), pix)
        assert (moved - p0).abs().max() < 1e-4
        lo, hi = b["bounds"][:, 0], b["bounds"][:, 1]
        bigger_box = {**b, "bounds": torch.stack([lo - (hi - lo), hi + (hi - lo)], 1)}  # longer rays: more voxels
        assert model.mean_samples_per_ray(bigger_box)[0] > model.mean_samples_per_ray(b)[0]
        assert not torch.allclose(model.render(model.prepare(bigger_box), pix), p0)
        twice = {**b, "tgt_pos": b["tgt_pos"] * 2, "src_pos": b["src_pos"] * 2, "gw_pos": b["gw_pos"] * 2}
        assert not torch.allclose(model.render(model.prepare(twice), pix), p0)
        # the ray direction enters each voxel's query
        assert model.query_direction.in_features == 63 and model.query_direction.weight.abs().sum() > 0


def test_voxels_are_encoded_by_distance_so_weights_do_not_depend_on_the_cap(tiny):
    """No table sized by max_samples: a model with another cap loads the same weights (strict) and gives the
    same prediction where neither cap binds; a voxel's code follows its distance in wavelengths."""
    a, b_ = _small(max_samples=64), _small(max_samples=8)
    assert not any("voxel_index" in k for k in a.state_dict())
    b_.load_state_dict(a.state_dict(), strict=True)
    batch = _eval_batch(tiny)
    assert max(a.samples_per_ray(batch)) <= 8  # the tiny scene at 915 MHz needs fewer voxels than either cap
    pix = torch.arange(0, 32400, 211).expand(2, -1)
    with torch.no_grad():
        assert torch.equal(a.render(a.prepare(batch), pix), b_.render(b_.prepare(batch), pix))
        t = a.ray_table(batch, 0)
        p = torch.tensor([5, 4000])
        S = int(t["samples"][p[0]])
        p = p[t["samples"][p] == S]
        _, code = a._voxel_inputs(
            p,
            t["t_in"][p],
            t["step"][p],
            batch["wavelength"][:1].expand(len(p)),
            batch["scene_index"][:1].expand(len(p)),
            S,
        )
    from graf.geometry.encoding import sinusoidal_encoding

    dist = t["t_in"][p][:, None] + (torch.arange(S) + 0.5) * t["step"][p][:, None]
    expect = a.voxel_distance(sinusoidal_encoding(dist / batch["wavelength"][0], a.d_model))
    assert torch.allclose(code, expect)
