"""RF Gaussian splatting as a per-scene correction of KNN (``model=rf_gs_knn``: ``base: knn``): the Gaussians are
added to KNN's inverse-distance mean of the neighbors' spectra."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate

from graf.models.knn import KNNModule
from graf.models.rf_gs import RFGSModule
from graf.run.train import train
from tests.models.test_rf_gs import SMALL, tiny_batch

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture
def tiny(make_scene):
    return tiny_batch(make_scene, L=3)


def test_the_preset_is_rf_gs_on_a_knn_base(compose_cfg):
    cfg = compose_cfg("train", ("model=rf_gs_knn",)).model
    plain = compose_cfg("train", ("model=rf_gs",)).model
    assert cfg.base == "knn" and plain.base == "none" and cfg.init_amplitude == 0.0
    assert {k for k in cfg if cfg[k] != plain[k]} == {"base", "init_amplitude"}  # every other setting as rf_gs
    model = instantiate(cfg)
    assert model.method == "rf-gs-knn" and model.per_scene and model.uses_neighbors  # its test measures reliance


def test_a_bad_base_is_refused_in_one_line():
    with pytest.raises(ValueError, match=r"model\.base='idw'") as info:
        RFGSModule(**{**SMALL, "base": "idw"})
    assert "\n" not in str(info.value)


def test_with_zero_amplitudes_it_predicts_knn_exactly(tiny):
    torch.manual_seed(0)
    settings = {**SMALL, "base": "knn", "init_amplitude": 0.0, "head_init": 0.0}
    model = RFGSModule(**settings).eval()
    knn = KNNModule(weighting="idw", power=1.0, ridge=1e-3)
    with torch.no_grad():
        ours, theirs = model.predict_spectra(tiny), knn.predict_spectra(tiny).float().clamp(0, 1)
    assert torch.equal(ours, theirs)
    model.chunk_spectra = 3  # chunks carry the neighbors with the targets
    with torch.no_grad():
        assert torch.equal(model.predict_spectra(tiny), theirs)


def test_gradients_reach_every_parameter_and_a_step_moves_it_off_knn(tiny):
    torch.manual_seed(0)
    model = RFGSModule(**{**SMALL, "base": "knn", "init_amplitude": 0.0})
    model.log = lambda *a, **k: None
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    before = model.training_step(tiny, 0)
    before.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert model.field.amplitude.grad.abs().sum() > 0  # zero amplitudes still learn (their shape is the gradient)
    for _ in range(5):
        opt.step()
        opt.zero_grad()
        loss = model.training_step(tiny, 0)
        loss.backward()
    assert loss < before  # the correction lowers KNN's error on the batch it is fitted to


def test_two_training_steps_through_the_real_configs(compose_cfg):
    overrides = ("scene=rfid_s23", "model=rf_gs_knn", "data.batch_size=2", "baselines={}", "data.test_subset=2")
    cfg = compose_cfg("train", (*overrides, "trainer.max_steps=2", "plot_count=0"))
    metrics, run = train(cfg)
    r = json.loads((Path(cfg.paths.output_dir) / "results.json").read_text())
    assert r["method"] == "rf-gs-knn" and r["global_step"] == 2
    assert math.isfinite(float(metrics["test/psnr"])) and metrics["test/reliance_db"] is not None
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    loaded = RFGSModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    batch = run.built.datamodule.eval_batch([0, 1])
    with torch.no_grad():
        assert loaded.base == "knn" and torch.equal(
            loaded.predict_spectra(batch), run.built.model.cpu().eval().predict_spectra(batch)
        )
