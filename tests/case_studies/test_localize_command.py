"""graf-localize (issue 24, part 4) on real runs of the embedded scene: the localizer from random initialisation
and pre-trained on each run's synthesized spectra, nothing trained on a test position or its synthesized copy."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

SMALL = ["n_synth=48", "seeds=[0]", "localizer.pretrain_steps=10", "localizer.train_steps=10", "threads=1"]


def _run(module: str, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr[-2000:]
    return p


def _check_group(g: dict, inits: set[str]) -> None:
    assert g["scene"] == "rfid_s23" and g["n_measured"] == 160 and g["n_test"] == 40 and g["n_synth"] == 48
    assert set(g["inits"]) == inits
    for r in g["inits"].values():
        assert 0.0 < r["median_m"] <= r["p90_m"] < 10.0 and len(r["per_seed"]) == 1
    # no synthetic position within half a wavelength (0.5 x 0.3276 m) of a test position
    assert g["min_gap_m"] == pytest.approx(0.5 * 0.32764, rel=1e-3)
    assert g["synthetic_min_distance_to_test_m"] >= g["min_gap_m"]


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_graf_localize_on_a_knn_run_resumes_and_reports_each_initialisation(tmp_path):
    run, out, data = tmp_path / "knn", tmp_path / "loc", tmp_path / "data"
    _run("graf.cli.evaluate", "model=knn", "logger=none", "plot_count=0", f"hydra.run.dir={run}", f"data_root={data}")
    p = _run("graf.cli.case_studies.localization", f"runs=[{run}]", *SMALL, f"hydra.run.dir={out}", f"data_root={data}")
    res = json.loads((out / "results.json").read_text())
    (g,) = res["groups"]
    _check_group(g, {"random", "knn"})
    # the synthesizer's quality is its predictions at the test positions: KNN's test PSNR of its own run
    knn_psnr = json.loads((run / "results.json").read_text())["metrics"]["test/psnr"]
    assert g["inits"]["knn"]["quality_psnr"] == pytest.approx(knn_psnr, abs=1e-3)
    assert (out / "localize.png").is_file() and "| rfid_s23 | 160 | knn |" in p.stdout
    assert g["inits"]["knn"]["quality_n_test"] == 40
    assert 0 < g["seconds"] <= res["seconds"]  # the group's wall time, and the command's over its invocations
    # a second invocation finds the group done and trains nothing again
    p = _run("graf.cli.case_studies.localization", f"runs=[{run}]", *SMALL, f"hydra.run.dir={out}", f"data_root={data}")
    assert "already in" in p.stderr + p.stdout
    assert json.loads((out / "results.json").read_text())["groups"] == res["groups"]


@pytest.mark.slow
def test_graf_localize_loads_a_trained_run_from_its_checkpoint(tmp_path):
    run, out, data = tmp_path / "kdl", tmp_path / "loc", tmp_path / "data"
    _run("graf.cli.train", "model=knn_dl", "trainer.max_steps=2", "logger=none", "plot_count=0", "reliance=false",
         f"hydra.run.dir={run}", f"data_root={data}")  # fmt: skip
    assert (run / "checkpoints" / "last.ckpt").is_file()
    _run("graf.cli.case_studies.localization", f"runs=[{run}]", *SMALL, f"hydra.run.dir={out}", f"data_root={data}")
    (g,) = json.loads((out / "results.json").read_text())["groups"]
    _check_group(g, {"random", "knn-dl", "knn"})  # KNN on the same pool joins the trained run's group
    assert np.isfinite(g["inits"]["knn-dl"]["quality_psnr"])


def test_a_measured_set_holding_a_test_position_is_refused():
    from graf.case_studies.localization import check_disjoint
    from graf.errors import ConfigError

    test = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    with pytest.raises(ConfigError, match="measured set holds 1 position"):
        check_disjoint(np.array([[0.5, 0.5, 0.5], [1.0, 1.0, 1.0]]), test, 1e-9, "measured set")


@pytest.mark.slow
def test_graf_localize_quality_on_a_jobs_own_test_budget_equals_its_test_psnr(tmp_path):
    """quality_test_count: a run tested on the first 12 test spectra (data.test_subset=12 with
    test_subset_seed=null, as the density jobs test their first 32) gets that run's test PSNR as its synthesis
    quality; the localizers still see all 40."""
    run, out, data = tmp_path / "knn", tmp_path / "loc", tmp_path / "data"
    _run("graf.cli.evaluate", "model=knn", "logger=none", "plot_count=0", "data.batch_size=4",
         "data.test_subset=12", "data.test_subset_seed=null", f"hydra.run.dir={run}", f"data_root={data}")  # fmt: skip
    res = json.loads((run / "results.json").read_text())
    n = res["n_test"]
    assert n == 12
    _run("graf.cli.case_studies.localization", f"runs=[{run}]", *SMALL, f"quality_test_count={n}",
         f"hydra.run.dir={out}", f"data_root={data}")  # fmt: skip
    (g,) = json.loads((out / "results.json").read_text())["groups"]
    assert g["n_test"] == 40 and g["inits"]["knn"]["quality_n_test"] == n
    assert g["inits"]["knn"]["quality_psnr"] == pytest.approx(res["metrics"]["test/psnr"], abs=1e-3)
    # the same folder with another setting, or more quality spectra than the test split holds: one line each
    for bad in ("quality_test_count=5", "quality_test_count=41"):
        out2 = out if bad.endswith("5") else tmp_path / "loc2"
        p = subprocess.run([sys.executable, "-m", "graf.cli.case_studies.localization", f"runs=[{run}]", *SMALL, bad,
                            f"hydra.run.dir={out2}", f"data_root={data}"], capture_output=True, text=True)  # fmt: skip
        assert p.returncode != 0
        assert ("other quality_test_count" if bad.endswith("5") else "test split holds 40") in p.stderr + p.stdout
