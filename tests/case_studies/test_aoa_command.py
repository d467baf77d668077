"""graf-aoa on a real run: KNN tested on the embedded scene with its predictions saved, then the AoA errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_graf_aoa_reads_a_saved_run_and_reports_the_three_errors(tmp_path):
    py = sys.executable
    run = tmp_path / "knn"
    p = subprocess.run(
        [py, "-m", "graf.cli.evaluate", "model=knn", "save_predictions=true", "logger=none", "plot_count=0",
         f"hydra.run.dir={run}", f"data_root={tmp_path / 'data'}"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    out = tmp_path / "aoa"
    p = subprocess.run(
        [py, "-m", "graf.cli.case_studies.aoa", f"runs=[{run}]", f"hydra.run.dir={out}"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    r = json.loads((out / "results.json").read_text())["runs"][0]
    assert r["method"] == "knn" and r["scene"] == "rfid_s23" and r["n"] == 40
    for k in ("pred_vs_geometry", "true_vs_geometry", "pred_vs_true"):
        assert 0.0 <= r[k]["median"] <= r[k]["p90"] <= 180.0
        assert len(r["per_spectrum"][k]) == 40
    assert r["test_reliance_db"] is not None and (out / "aoa_cdf.png").is_file() and (out / "aoa.md").is_file()
    assert r["n_measured"] == 160 and "| knn | rfid_s23 | 160 | 40 |" in p.stdout  # the whole training split


def test_graf_aoa_names_a_folder_without_predictions(tmp_path):
    from graf.case_studies.aoa import run_errors
    from graf.errors import ConfigError

    (tmp_path / "results.json").write_text("{}")
    with pytest.raises(ConfigError, match=r"predictions.npz: missing .*save_predictions=true"):
        run_errors(Path(tmp_path), None)


@pytest.mark.slow  # two commands' start-up and a KNN evaluation (about 40 s here)
def test_graf_aoa_adds_the_knn_baseline_on_the_runs_own_positions_and_neighbors(tmp_path):
    """A study job keeps only its model's predictions; graf-aoa re-evaluates the KNN it was tested beside
    (``baselines.knn``) on the same test positions and neighbors: its PSNR is the run's own KNN figure."""
    from graf.case_studies.aoa import knn_errors

    run = tmp_path / "run"
    p = subprocess.run(
        [sys.executable, "-m", "graf.cli.train", "model=knn", "save_predictions=true", "logger=none", "plot_count=0",
         "data.test_subset=12", f"hydra.run.dir={run}", f"data_root={tmp_path / 'data'}"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    res = json.loads((run / "results.json").read_text())
    row = knn_errors(run, str(tmp_path / "data"))
    assert row["method"] == "knn" and row["n"] == res["n_test"] < 40  # the run's limited test positions
    assert row["test_psnr"] == pytest.approx(res["metrics"]["test/psnr"], abs=1e-6)
