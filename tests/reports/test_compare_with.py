"""graf-report's ``compare_with``: a study's methods compared, on the same test spectra, with the trained methods of
another study's record (a per-scene method against GRaF's matrix); only the cells the two share; the other record's
method gets no rows of its own; a KNN that differs between the two (other spectra) is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from graf.reports.intervals import write_intervals
from graf.run.per_spectrum import write_per_spectrum

IDS = list(range(500, 620))


def _job(folder, method: str, scene: str, eval_scene: str, values: dict, seed: int = 0) -> None:
    """One job's records: ``values`` {method: PSNR per spectrum} (the trained one and KNN beside it)."""
    folder.mkdir(parents=True)
    rows = [
        {"eval_scene": eval_scene, "method": m, "id": i, "mse": 10 ** (-v / 10), "psnr": v, "ssim": 0.5, "lpips": 0.3}
        for m, psnr in values.items()
        for i, v in zip(IDS, psnr)
    ]
    write_per_spectrum(folder / "per_spectrum.csv.gz", rows)
    result = {
        "method": method,
        "scene": scene,
        "train_scenes": [scene],
        "train_bands_hz": [2.412e9],
        "band_hz": 2.412e9,
        "metrics": {"test/psnr": 0.0},
        "config": {"seed": seed, "sim_num_tx": None, "neighbors": {"L": 10}},
        "per_spectrum": "per_spectrum.csv.gz",
        "evaluations": [{"eval_scene": eval_scene, "band_hz": 2.412e9, "metrics": {}, "baselines": {}}],
    }
    (folder / "results.json").write_text(json.dumps(result))


@pytest.fixture
def two_studies(tmp_path):
    """This study: rf-gs within conference_v1 (2 seeds), KNN beside.  The other: GRaF trained on conference_v1,
    tested on conference_v1 (shared cell) and office_v1 (not shared).  rf-gs is 1.0 dB above GRaF, GRaF 0.5 above
    KNN, on every spectrum, plus noise."""
    rng = np.random.default_rng(3)
    knn = {s: rng.normal(20.0, 3.0, len(IDS)) for s in ("conference_v1", "office_v1")}
    for seed in (0, 1):
        rf = knn["conference_v1"] + 1.5 + rng.normal(0, 0.1, len(IDS))
        _job(tmp_path / "ours" / f"seed={seed}", "rf-gs", "conference_v1", "conference_v1",
             {"rf-gs": rf, "knn": knn["conference_v1"]}, seed)  # fmt: skip
    for test in ("conference_v1", "office_v1"):
        graf = knn[test] + 0.5 + rng.normal(0, 0.1, len(IDS))
        _job(tmp_path / "theirs" / f"eval={test}", "graf", "conference_v1", test, {"graf": graf, "knn": knn[test]})
        dl = knn[test] + 0.1 + rng.normal(0, 0.1, len(IDS))  # a reference of every study (REFERENCES) as well
        _job(tmp_path / "theirs" / f"dl,eval={test}", "knn-dl", "conference_v1", test, {"knn-dl": dl, "knn": knn[test]})
    return tmp_path


def test_a_method_of_another_record_is_a_reference_on_the_shared_cells(two_studies):
    rows = write_intervals(two_studies / "ours", two_studies / "out", [two_studies / "theirs"])
    psnr = [r for r in rows if r["metric"] == "psnr"]
    assert [(r["method"], r["eval_scene"]) for r in psnr] == [("rf-gs", "conference_v1")]  # none of theirs, no office
    row = psnr[0]
    assert row["vs_graf"]["low"] < 1.0 < row["vs_graf"]["high"] and row["vs_graf"]["verdict"] == "ahead"
    assert row["vs_knn"]["low"] < 1.5 < row["vs_knn"]["high"]
    assert row["vs_graf"]["n_spectra"] == len(IDS) and row["vs_graf"]["n_seeds"] == 2
    assert row["vs_knn-dl"]["low"] < 1.4 < row["vs_knn-dl"]["high"]  # KNN-DL's column filled from the other record
    record = json.loads((two_studies / "out" / "intervals.json").read_text())
    assert record["compared_with"]["methods"] == ["graf", "knn-dl"]
    head = (two_studies / "out" / "intervals.md").read_text().split("\n\n")[1].splitlines()[0]
    assert head.count("- graf") == 1 and head.count("KNN-DL") == 1 and "knn-dl" not in head


def test_without_compare_with_the_record_is_the_studys_own(two_studies):
    rows = write_intervals(two_studies / "ours", two_studies / "out")
    assert all("vs_graf" not in r for r in rows)
    assert "- graf" not in (two_studies / "out" / "intervals.md").read_text()


def test_a_knn_on_other_spectra_is_refused(two_studies):
    knn = np.random.default_rng(9).normal(20.0, 3.0, len(IDS))  # the other record's KNN: other values, both its jobs
    for job, method in (("eval=conference_v1", "graf"), ("dl,eval=conference_v1", "knn-dl")):
        other = two_studies / "theirs" / job / "per_spectrum.csv.gz"
        other.unlink()
        rows = [
            {"eval_scene": "conference_v1", "method": m, "id": i, "mse": 0.01, "psnr": float(v), "ssim": 0.5}
            | {"lpips": 0.3}
            for m in (method, "knn")
            for i, v in zip(IDS, knn)
        ]
        write_per_spectrum(other, rows)
    with pytest.raises(ValueError, match="KNN on .* differs from this study's"):
        write_intervals(two_studies / "ours", two_studies / "out", [two_studies / "theirs"])


def test_a_missing_record_is_named(two_studies):
    with pytest.raises(FileNotFoundError, match="nowhere: no such study record"):
        write_intervals(two_studies / "ours", two_studies / "out", [two_studies / "nowhere"])
