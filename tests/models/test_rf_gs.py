"""RF Gaussian splatting (graf.models.rf_gs): the rasterizer against closed forms (the azimuth seam, the grid's
edges, reduced precision), gradients to every parameter, densification and checkpoints of a grown Gaussian count,
two training steps through the real configs, and the per-scene refusals."""

from __future__ import annotations

import inspect
import json
import math
from pathlib import Path

import lightning as L
import pytest
import torch
from hydra.utils import instantiate

import graf.models.rf_gs as rf_gs_pkg
from graf.bands import Band
from graf.cli import evaluate as graf_eval
from graf.cli import train as graf_train
from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector
from graf.data.scenes import NeRF2Scene
from graf.errors import ConfigError
from graf.models.base import read_checkpoint
from graf.models.rf_gs import RFGSModule, render, render_dense, split_plan, split_rows
from graf.models.rf_gs.rasterizer import ELEVATION_EDGES, WIDE, azimuth_profiles, elevation_profiles
from graf.run.train import train
from tests.app.test_entry_points import _main as run_main

UHF = Band(name="915mhz", frequency_hz=915e6)
SMALL = {"num_gaussians": 16, "max_gaussians": 64, "depth": 2, "width": 16, "pe_freqs": 4}
QUICK = ("logger=none", "plot_count=0", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false")


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def tiny_batch(make_scene, L: int) -> dict:
    """Four targets of a 16-transmitter scene with up to L neighbors each."""
    dm = SpectrumDataModule(
        NeRF2Scene(name="tiny", path=str(make_scene(n=16))), UHF, NeighborSelector(L=L, L_train=(1, L), radius=10.0)
    )
    dm.setup()
    return dm.eval_batch([0, 1, 2, 3])


@pytest.fixture
def tiny(make_scene):
    return tiny_batch(make_scene, L=2)


def _one(**g) -> list[torch.Tensor]:
    """One Gaussian as the rasterizer's ``[1, 1]`` inputs (elevation, azimuth, sigma_el, sigma_az, amplitude)."""
    return [torch.tensor([[float(g[k])]], dtype=torch.float64) for k in ("e", "a", "s", "t", "w")]


def _closed_form(e, a, s, t, w) -> torch.Tensor:
    """``w exp(-(E - e)^2 / 2 s^2) * sum_j exp(-(A - a + 360 j)^2 / 2 t^2)`` on the grid (float64, seven turns)."""
    el = torch.arange(1, 91, dtype=torch.float64)[:, None]
    az = torch.arange(1, 361, dtype=torch.float64)[None, :]
    turns = sum(torch.exp(-((az - a + 360.0 * j) ** 2) / (2 * t**2)) for j in range(-3, 4))
    return w * torch.exp(-((el - e) ** 2) / (2 * s**2)) * turns


def _batch(n: int = 2) -> dict:
    return {"tgt_pos": torch.rand(n, 3), "bounds": torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]).expand(n, 2, 3)}


# ---------------------------------------------------------------------------------------------- the rasterizer
@pytest.mark.parametrize(
    "g",
    [
        {"e": 30.2, "a": 100.7, "s": 3.0, "t": 5.0, "w": 0.8},  # in the middle of the grid
        {"e": 45.0, "a": 359.5, "s": 2.0, "t": 2.0, "w": 1.0},  # straddling the seam: columns 359 and 0 alike
        {"e": 45.0, "a": -0.5, "s": 2.0, "t": 2.0, "w": 1.0},  # the same Gaussian, its mean written below 0
        {"e": 10.0, "a": 180.0, "s": 4.0, "t": 55.0, "w": -0.3},  # wide: both turns of the wrapped normal count
        {"e": 90.5, "a": 20.0, "s": 2.0, "t": 3.0, "w": 1.0},  # at the zenith edge: the half on the grid
    ],
)
def test_one_gaussian_matches_its_closed_form(g):
    want = _closed_form(**g)
    got = render(*_one(**g))[0]
    assert got.shape == (90, 360) and got.dtype == torch.float32
    assert torch.allclose(got.double(), want, atol=5e-6 * abs(g["w"]))  # float32 means: ~1e-6 deg
    if g["a"] in (359.5, -0.5):  # the seam: azimuth 1 deg (column 0) lit as azimuth 358 deg (column 357)
        r = int(g["e"]) - 1
        assert got[r, 0] > 0.7 * got[r].max() and torch.isclose(got[r, 0], got[r, 357], rtol=1e-5)
    if g["e"] == 90.5:  # the mean at the edge: the top row is the brightest, and nothing wraps to the bottom
        assert got[89].max() == got.max() and got[0].abs().max() < 1e-20


def test_separable_render_equals_the_dense_sum_where_only_wide_ones_take_the_second_turn():
    torch.manual_seed(0)
    B, N = 2, 7
    g = [90 * torch.rand(B, N), 720 * torch.rand(B, N) - 180, 0.5 + 10 * torch.rand(B, N)]
    t = torch.tensor([1.0, 3.0, 10.0, WIDE - 1, WIDE + 1, 40.0, 60.0]).expand(B, N)  # the dense sum: both turns
    w = torch.randn(B, N)
    fast, dense = render(g[0], g[1], g[2], t, w), render_dense(g[0], g[1], g[2], t, w)
    assert torch.allclose(fast, dense, atol=1e-5)
    wide = azimuth_profiles(torch.zeros(1, 1), torch.full((1, 1), 60.0))[0, :, 0]
    assert torch.isclose(wide[179], 2 * torch.exp(torch.tensor(-0.5 * (180 / 60) ** 2)))  # the antipode: two turns


def test_the_written_out_backward_matches_autograd_of_the_dense_sum():
    """The profiles' backward (rasterizer._Profile) against autograd through render_dense, in float64: means
    beyond 360 and below 0, at the seam, narrow and wide (both turns) Gaussians, and the elevation edges."""
    torch.manual_seed(1)
    B = 2
    e = torch.tensor([[0.2, 30.0, 45.0, 90.7, 60.0, 12.0]], dtype=torch.float64).expand(B, 6) + torch.rand(B, 6)
    a = torch.tensor([[359.5, -0.5, 400.0, 180.0, 10.0, -250.0]], dtype=torch.float64).expand(B, 6) + torch.rand(B, 6)
    s = torch.tensor([[1.0, 3.0, 8.0, 2.0, 20.0, 0.5]], dtype=torch.float64).expand(B, 6).clone()
    t = torch.tensor([[2.0, WIDE + 1, 60.0, 1.0, 30.0, 5.0]], dtype=torch.float64).expand(B, 6).clone()
    w = torch.randn(B, 6, dtype=torch.float64)
    inputs = [x.clone().requires_grad_() for x in (e, a, s, t, w)]
    weights = torch.randn(B, 90, 360, dtype=torch.float64)
    el, az, sig_el, sig_az, amp = inputs  # the profiles themselves, in float64 (render computes in float32)
    separable = torch.matmul(elevation_profiles(el, sig_el) * amp[:, None, :], azimuth_profiles(az, sig_az).mT)
    fast = torch.autograd.grad((separable * weights).sum(), inputs)
    dense = torch.autograd.grad((render_dense(*inputs) * weights).sum(), inputs)
    for name, f, d in zip(("elevation", "azimuth", "sigma_el", "sigma_az", "amplitude"), fast, dense):
        assert torch.allclose(f, d, rtol=1e-9, atol=1e-9 * d.abs().max()), name


def test_bf16_autocast_renders_close_to_fp32():
    torch.manual_seed(0)
    model = RFGSModule(**SMALL).eval()
    b = _batch()
    with torch.no_grad():
        fp32 = model.render(b)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            bf16 = model.render(b)
    assert bf16.dtype == torch.float32 and torch.isfinite(bf16).all()
    assert (bf16 - fp32).abs().max() < 0.02 * fp32.abs().max()


# ---------------------------------------------------------------------------------------------- the module
def test_the_preset_is_the_constructor_and_the_method_is_per_scene(compose_cfg):
    from graf.models.base import Method

    params = set(inspect.signature(RFGSModule.__init__).parameters) - {"self"}
    cfg = compose_cfg("train", ("model=rf_gs",)).model
    assert set(cfg) - {"_target_"} == params
    model = instantiate(cfg)
    assert isinstance(model, Method) and model.method == "rf-gs" and model.per_scene and not model.uses_neighbors
    assert model.field.count == cfg.num_gaussians and model.has_trainable_parameters
    opt = model.configure_optimizers()["optimizer"]
    assert [g["lr"] for g in opt.param_groups] == [cfg.lr_means, cfg.lr]
    assert sum(len(g["params"]) for g in opt.param_groups) == len(list(model.parameters()))
    source = "".join(Path(f).read_text() for f in Path(rf_gs_pkg.__file__).parent.glob("*.py"))
    assert ".cuda(" not in source and '"cuda"' not in source  # the same code on any device


@pytest.mark.parametrize(
    "key, value",
    [
        ("num_gaussians", 0),
        ("max_gaussians", 8),  # below num_gaussians (16)
        ("depth", 0),
        ("pe_freqs", -1),
        ("sigma_max", 90.0),  # beyond what the wrapped normal's two turns render exactly
        ("sigma_min", 0.0),
        ("init_sigma", 100.0),
        ("max_shift", -1.0),
        ("lr", float("nan")),
        ("lr_means", 0.0),
        ("lr_decay", 2.0),
        ("decay_steps", 0),
        ("densify_every", -1),
        ("densify_fraction", 1.5),
        ("prune_amplitude", float("inf")),
        ("chunk_spectra", 0),
    ],
)
def test_a_bad_setting_is_refused_in_one_line_naming_it(key, value):
    with pytest.raises(ValueError, match=rf"model\.{key}") as info:
        RFGSModule(**{**SMALL, key: value})
    assert "\n" not in str(info.value)


def test_a_bad_setting_on_the_command_line_is_one_line_with_exit_code_2(monkeypatch, capsys, tmp_path):
    out = tmp_path / "run"
    args = ("model=rf_gs", "model.sigma_max=100", "trainer.max_steps=1", *QUICK, f"hydra.run.dir={out}")
    code, _, err = run_main(monkeypatch, capsys, graf_train.main, *args)
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("[")]
    assert code == 2 and lines[0].startswith("error: model.sigma_max") and "Traceback" not in err, err
    assert not (out / "results.json").exists()


def test_gradients_reach_every_parameter():
    torch.manual_seed(0)
    model = RFGSModule(**SMALL, sigma_max=40.0, init_sigma=30.0)  # wide: the second azimuth turn is in the graph
    b = {**_batch(3), "tgt_spectrum": torch.rand(3, 90, 360)}
    model.log = lambda *a, **k: None
    model.training_step(b, 0).backward()
    named = dict(model.named_parameters())
    assert {"field.elevation", "field.azimuth", "field.log_sigma", "field.amplitude", "field.head_weight"} <= set(named)
    assert any(k.startswith("field.trunk.") for k in named)
    for name, p in named.items():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_one_gaussian_and_means_beyond_the_edges():
    torch.manual_seed(0)
    model = RFGSModule(**{**SMALL, "num_gaussians": 1}).eval()
    with torch.no_grad():
        model.field.elevation.fill_(120.0)  # beyond the zenith edge: clamped to it, half of it on the grid
        model.field.azimuth.fill_(-725.0)  # any real azimuth is taken modulo 360
        g = model.gaussians(_batch(1))
        pred = model.predict_spectra(_batch(1))
    assert g["elevation"].item() == ELEVATION_EDGES[1] and pred.shape == (1, 90, 360)
    assert torch.isfinite(pred).all() and (pred >= 0).all() and (pred <= 1).all()
    assert pred[0, 89].argmax().item() == 354  # -725 = 355 (mod 360): column 354
    model.field.elevation.data.fill_(-50.0)  # below the lower edge: clamped to 0.5 deg, the bottom row brightest
    with torch.no_grad():
        raw = model.render(_batch(1))[0]
    assert raw.abs().amax(dim=1).argmax().item() == 0


def test_optimisation_lowers_the_loss_on_a_fixed_batch(tiny):
    torch.manual_seed(0)
    model = RFGSModule(num_gaussians=128, depth=2, width=32, pe_freqs=4)
    model.log = lambda *a, **k: None
    opt = torch.optim.Adam(
        [{"params": [model.field.elevation, model.field.azimuth], "lr": 0.2}]
        + [{"params": [p for n, p in model.named_parameters() if not n.endswith(("elevation", "azimuth"))]}],
        lr=1e-2,
    )
    losses = []
    for _ in range(30):
        loss = model.training_step(tiny, 0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses) and losses[-1] < 0.5 * losses[0]


# ---------------------------------------------------------------------------------------------- densify, checkpoints
def test_the_plan_prunes_the_faint_and_splits_the_largest_gradients_within_the_cap():
    score, magnitude = torch.tensor([0.0, 5.0, 1.0, 2.0]), torch.tensor([1.0, 1.0, 1.0, 1e-5])
    keep, split = split_plan(score, magnitude, 0.25, 1e-3, 64)
    assert keep.tolist() == [0, 1, 2] and split.tolist() == [1]  # 3 is faint; 1 has the largest gradient
    assert split_plan(score, magnitude, 1.0, 1e-3, 64)[1].tolist() == [1, 2]  # never one of zero gradient
    assert split_plan(score, magnitude, 1.0, 1e-3, 4)[1].tolist() == [1]  # the cap: 3 kept + 1 split
    keep, split = split_plan(score, torch.zeros(4), 0.0, 1e-3, 64)
    assert keep.numel() == 1 and split.numel() == 0  # all faint: the strongest is kept


def test_a_split_keeps_the_gaussians_integral_mean_and_variance():
    model = RFGSModule(**{**SMALL, "num_gaussians": 1, "head_init": 0.0})  # no offsets: the base Gaussian itself
    f = model.field
    with torch.no_grad():
        f.elevation.fill_(45.0)
        f.azimuth.fill_(180.0)
        f.log_sigma.copy_(torch.log(torch.tensor([[3.0, 8.0]])))  # wider in azimuth: split along azimuth
        before = model.render(_batch(1))[0].double()
    index, moved = split_rows(f, torch.tensor([0]), torch.tensor([0]))
    assert index.tolist() == [0, 0] and f.count == 2 and set(moved.values()) == set(f.per_gaussian())
    assert f.azimuth.tolist() == [176.0, 184.0] and torch.allclose(f.log_sigma[:, 0], torch.log(torch.tensor(3.0)))
    with torch.no_grad():
        after = model.render(_batch(1))[0].double()
    az = torch.arange(1, 361, dtype=torch.float64)
    moments = []
    for img in (before, after):
        w = img.sum(0)
        mean = (w * az).sum() / w.sum()
        moments.append(torch.stack([w.sum(), mean, (w * (az - mean) ** 2).sum() / w.sum()]))
    assert torch.allclose(moments[1], moments[0], rtol=1e-4)  # integral, mean and variance along azimuth


def test_densify_carries_adams_moments_and_training_goes_on():
    torch.manual_seed(0)
    model = RFGSModule(**SMALL, densify_every=1, densify_fraction=0.25, prune_amplitude=0.0)
    model.log = lambda *a, **k: None
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    b = {**_batch(2), "tgt_spectrum": torch.rand(2, 90, 360)}
    for _ in range(2):
        model.training_step(b, 0).backward()
        model.on_after_backward()
        opt.step()
        opt.zero_grad()
    old = model.field.amplitude
    moment = opt.state[old]["exp_avg"].clone()
    assert model.densify_and_prune(opt) == 20  # 16 + a quarter of them split
    new = model.field.amplitude
    assert new is not old and old not in opt.state and any(new is p for p in opt.param_groups[0]["params"])
    assert opt.state[new]["exp_avg"].shape == (20,) and set(opt.state[new]["exp_avg"][:12].tolist()) <= set(
        moment.tolist()
    )
    model.training_step(b, 0).backward()  # the next step's backward and update run on the new count
    opt.step()
    assert model.field.amplitude.shape == (20,)


def _lightning_checkpoint(model: RFGSModule, path: Path) -> Path:
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_steps=0)
    trainer.strategy.connect(model)
    trainer.save_checkpoint(path, weights_only=True)
    return path


def test_a_checkpoint_with_a_grown_count_loads_and_predicts_identically(tmp_path):
    torch.manual_seed(0)
    model = RFGSModule(**SMALL).eval()
    model.stats = {"score": torch.rand(16), "magnitude": torch.ones(16), "steps": 1}
    assert model.densify_and_prune() == 16 + math.ceil(model.densify_fraction * 16)
    path = _lightning_checkpoint(model, tmp_path / "grown.ckpt")
    loaded = RFGSModule.load_from_checkpoint(path, map_location="cpu", weights_only=True).eval()
    assert loaded.hparams.num_gaussians == 16 and loaded.field.count == model.field.count
    b = _batch(3)
    with torch.no_grad():
        assert torch.equal(loaded.predict_spectra(b), model.predict_spectra(b))
    fresh = RFGSModule(**SMALL).eval()  # the path of finetune.init_from: a plain load_state_dict
    fresh.load_state_dict(read_checkpoint(path)["state_dict"], strict=True)
    with torch.no_grad():
        assert torch.equal(fresh.predict_spectra(b), model.predict_spectra(b))


# ---------------------------------------------------------------------------------------------- real configs
@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_two_training_steps_through_the_real_configs_a_grown_checkpoint_and_no_zero_shot(
    compose_cfg, make_scene, monkeypatch, capsys
):
    overrides = (
        "scene=rfid_s23",
        "model=rf_gs",
        "model.densify_every=1",  # densify at every step: the checkpoint holds a grown count
        "model.densify_until=1.0",
        "data.batch_size=2",
        "baselines={}",
        "plot_count=1",
        "data.test_subset=2",
    )
    cfg = compose_cfg("train", (*overrides, "trainer.max_steps=2"))
    metrics, run = train(cfg)
    out = Path(cfg.paths.output_dir)
    r = json.loads((out / "results.json").read_text())
    assert r["method"] == "rf-gs" and r["global_step"] == 2
    assert all(math.isfinite(float(v)) for k, v in metrics.items() if "swapped" not in k and "reliance" not in k)
    assert metrics["test/reliance_db"] is None  # reads no neighbors: no reliance to measure
    model = run.built.model.cpu().eval()
    assert model.field.count > cfg.model.num_gaussians  # two densification passes
    ckpt = out / "checkpoints" / "last.ckpt"
    loaded = RFGSModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    assert loaded.hparams == model.hparams and loaded.field.count == model.field.count
    batch = run.built.datamodule.eval_batch([0, 1])
    with torch.no_grad():
        assert torch.equal(loaded.predict_spectra(batch), model.predict_spectra(batch))
    # resumed for a third step: the grown count loads, and Adam's state with it
    again = compose_cfg(
        "train",
        (*overrides, "trainer.max_steps=3", f"ckpt_path={ckpt}", f"paths.output_dir={out.parent / 'resumed'}"),
    )
    _, resumed = train(again)
    assert resumed.built.trainer.global_step == 3 and resumed.built.model.field.count > model.field.count
    # graf-eval of this checkpoint on another scene: refused in one line, before anything is tested
    other = make_scene(n=16, name="other")
    capsys.readouterr()  # what the training run said (a log handler of an earlier command may have complained)
    code, _, err = run_main(
        monkeypatch,
        capsys,
        graf_eval.main,
        f"ckpt_path={ckpt}",
        "scene=nerf2",
        f"scene.nerf2.path={other}",
        "band=915mhz",
        "neighbors=fixed",
        "neighbors.L=2",
        *QUICK,
        f"hydra.run.dir={out.parent / 'zero_shot'}",
    )
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("[")]
    assert code == 2 and "Traceback" not in err, err
    assert lines[0].startswith("error: RFGSModule is a per-scene method and was not trained on nerf2"), err
    assert not (out.parent / "zero_shot" / "results.json").exists()


def test_training_on_several_scenes_or_testing_on_another_is_refused_before_training(compose_cfg, make_scene):
    other = make_scene(n=16, name="other")
    cases = {
        "eval_scene": ("scene=rfid_s23", "eval_scene=nerf2", f"eval_scene.nerf2.path={other}"),
        "pooled": ("scene=[rfid_s23,nerf2]", f"scene.nerf2.path={other}"),
    }
    for case, overrides in cases.items():
        common = ("model=rf_gs", "trainer.max_steps=1", "baselines={}", "band=915mhz", "neighbors=fixed")
        cfg = compose_cfg("train", (*common, "neighbors.L=2", *overrides))
        with pytest.raises(ConfigError, match="per-scene method") as info:
            train(cfg)
        assert "\n" not in str(info.value), case
        assert not (Path(cfg.paths.output_dir) / "checkpoints").exists(), case  # refused before any step


def test_the_studies_list_it_where_a_per_scene_method_belongs():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from graf.app.config import CONF_DIR
    from graf.studies.curves import regime_methods

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        curves, bench, pareto = compose("curves"), compose("bench"), compose("pareto")
    GlobalHydra.instance().clear()
    within = ("rfid_sparse", "paper_within")  # the learning curves: validated within the scene it trains on
    assert all("rf_gs" in regime_methods(curves, r) for r in within)
    assert all("rf_gs" not in regime_methods(curves, r) for r in curves.regimes if r not in within)
    assert curves.methods.rf_gs.schedule == "model.decay_steps"
    assert bench.models.rf_gs._target_ == "graf.models.rf_gs.RFGSModule"
    # at the base budget: no schedule of its own, so it decays over the run's steps as the base GRaF does
    assert list(pareto.points.rf_gs.overrides) == ["model=rf_gs"] and "method" in pareto.reference_knobs
    assert not any(o.startswith(("model.decay_steps", "trainer.max_steps")) for o in pareto.base)


# ---------------------------------------------------------------------------------------------- limits, identity
def test_a_gaussian_count_beyond_the_memory_is_refused_before_it_is_allocated(monkeypatch, capsys, tmp_path):
    """Two million Gaussians: one line naming the setting, the count and the estimate (from the parameter
    tensors' rows), before any tensor of that size is made; at the command line exit code 2."""
    from types import SimpleNamespace

    from graf.models.rf_gs import gaussians, module
    from graf.models.rf_gs.gaussians import GaussianField

    field = GaussianField(3, 2, 16, 4, 3.0, 0.1, 0.5, 60.0, 45.0, 1e-3)
    row = sum(p[0].numel() * p.element_size() for p in field.per_gaussian())  # one Gaussian's row, in bytes
    assert gaussians.gaussian_bytes(16, 0) == gaussians.TRAINING_COPIES * row
    monkeypatch.setattr(module.psutil, "virtual_memory", lambda: SimpleNamespace(available=8 * 10**9))
    made = []
    monkeypatch.setattr(GaussianField, "reset", lambda self, n: made.append(n))
    with pytest.raises(ConfigError) as info:
        RFGSModule(**{**SMALL, "num_gaussians": 2_000_000, "max_gaussians": 2_000_000})
    need = 2_000_000 * gaussians.gaussian_bytes(16, 16)
    assert str(info.value) == (
        f"model.num_gaussians=2000000: needs at least {need / 1e9:.1f} GB (2,000,000 Gaussians x "
        f"{gaussians.gaussian_bytes(16, 16):,} bytes: their parameters at model.width=16, with gradients and Adam's "
        "moments, and 16 spectra rendered at once, model.chunk_spectra), more than the 8.0 GB this machine has "
        "free; lower it"
    )
    assert made == []  # refused before the Gaussians were drawn
    with pytest.raises(ConfigError, match=r"^model\.max_gaussians=2000000: needs at least"):  # densification's cap
        RFGSModule(**{**SMALL, "max_gaussians": 2_000_000})
    RFGSModule(**{**SMALL, "max_gaussians": 2_000_000, "densify_every": 0})  # never densified: never reached
    out = tmp_path / "run"
    args = ("model=rf_gs", "model.num_gaussians=2000000", "model.max_gaussians=2000000", *QUICK, f"hydra.run.dir={out}")
    code, _, err = run_main(monkeypatch, capsys, graf_train.main, *args)
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("[")]
    assert code == 2 and "Traceback" not in err and lines[0].startswith("error: model.num_gaussians=2000000: "), err


def test_a_checkpoint_tested_on_another_folder_of_its_scene_name_says_what_differs(
    compose_cfg, make_scene, monkeypatch, capsys
):
    """Trained on nerf2 from one folder, tested on nerf2 from another: the message names both folders and
    content fingerprints and what differs, not "was not trained on nerf2"."""
    trained, other = make_scene(n=16, name="here"), make_scene(n=16, name="there", seed=1)
    common = ("model=rf_gs", "scene=nerf2", "band=915mhz", "neighbors=fixed", "neighbors.L=2", "baselines={}")
    small = ("model.num_gaussians=16", "model.max_gaussians=16", "model.width=16", "model.depth=1", "plot_count=0")
    cfg = compose_cfg("train", (*common, *small, f"scene.nerf2.path={trained}", "trainer.max_steps=1"))
    train(cfg)
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    capsys.readouterr()
    code, _, err = run_main(
        monkeypatch,
        capsys,
        graf_eval.main,
        f"ckpt_path={ckpt}",
        *[a for a in common if a != "model=rf_gs" and a != "baselines={}"],
        f"scene.nerf2.path={other}",
        *QUICK,
        f"hydra.run.dir={Path(cfg.paths.output_dir).parent / 'other_folder'}",
    )
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("[")]
    assert code == 2 and "Traceback" not in err, err
    line = lines[0]
    assert line.startswith(
        "error: RFGSModule is a per-scene method, and the nerf2 given here is not the nerf2 it was trained on "
        "(its transmitter positions and spectra differ): here "
    ), line
    assert f"here {other} (content fingerprint " in line and f"trained on {trained} (content fingerprint " in line
