"""The density study (issue 24, part 2): its experiment composes to from-scratch runs on a measured fraction, and
graf-report turns such runs into metric-vs-spacing curves and the spacing a target PSNR needs."""

from __future__ import annotations

import json

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from graf.app.config import CONF_DIR
from graf.reports.rows import spacing_for
from graf.reports.study import make_report


def test_the_density_experiment_trains_from_scratch_on_a_measured_fraction():
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", ["experiment=density", "finetune=f20", "paths.output_dir=/tmp/x"])
    GlobalHydra.instance().clear()
    assert cfg.finetune.fraction == 0.2 and cfg.finetune.init_from is None  # no base model: from scratch
    assert OmegaConf.select(cfg, "study_steps") is None and cfg.study_budgets  # each model trains its budget
    assert cfg.baselines.knn
    assert cfg.save_predictions and cfg.callbacks.model_checkpoint  # its jobs feed graf-aoa and graf-localize
    assert cfg.data.test_subset == 32 and cfg.data.test_subset_seed is None  # the first 32 test spectra a job


def test_spacing_for_a_target_interpolates_where_the_curve_crosses_it():
    pts = {0.01: {"PSNR": 24.0}, 0.02: {"PSNR": 22.0}, 0.04: {"PSNR": 18.0}}
    got = spacing_for(pts, (25.0, 22.0, 20.0, 16.0))
    assert got["25"] is None  # never reached
    assert got["22"] == pytest.approx(0.02)
    assert got["20"] == pytest.approx(0.02 * 2**0.5)  # halfway from 22 to 18 dB, halfway in log spacing
    assert got["16"] == pytest.approx(0.04)  # reached at every measured spacing: the largest


def _result(method: str, fraction: float, spacing: float, psnr: float, knn_psnr: float) -> dict:
    m = {"test/psnr": psnr, "test/ssim": 0.7, "test/lpips": 0.2, "test/mse": 0.01, "test/reliance_db": 3.0}
    k = {**m, "test/psnr": knn_psnr}
    return {
        "method": method, "scene": "rfid_s23", "eval_scene": "rfid_s23", "within_scene": True, "n_test": 40,
        "band_hz": 915e6, "train_bands_hz": [915e6], "train_scenes": ["rfid_s23"], "global_step": 300,
        "metrics": m, "baselines": {"knn": {"metrics": k}}, "config": {"neighbors": {"L": 10}},
        "splits": {"measured_fraction": fraction, "measured_spacing_m": spacing},
    }  # fmt: skip


def test_graf_report_draws_a_density_study_against_the_survey_spacing(tmp_path):
    runs = tmp_path / "runs"
    for f, sp, p, kp in ((0.05, 0.05, 15.0, 14.0), (0.2, 0.023, 18.5, 17.0), (1.0, 0.007, 21.0, 20.5)):
        job = runs / f"model=graf,finetune=f{round(100 * f):02d}"
        job.mkdir(parents=True)
        (job / "results.json").write_text(json.dumps(_result("graf-ray-weights", f, sp, p, kp)))
    reference = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "report.yaml").reference)
    summary = make_report(runs, tmp_path / "out", reference)
    assert "vs_spacing_rfid_s23.png" in summary["figures"]
    curve = summary["vs_spacing"]["rfid_s23"]
    assert sorted(curve["graf-ray-weights"]) == [0.007, 0.023, 0.05] and sorted(curve["knn"]) == [0.007, 0.023, 0.05]
    need = summary["spacing_for_psnr"]["rfid_s23"]
    assert 0.007 < need["graf-ray-weights"]["20"] < 0.023 and need["knn"]["20"] < need["graf-ray-weights"]["20"]
    assert need["knn"]["22"] is None
    rows = json.loads((tmp_path / "out" / "rows.json").read_text())["rows"]
    assert {r["finetune"] for r in rows} == {"f05", "f20", "f100"}  # from-scratch fractions label the axis
