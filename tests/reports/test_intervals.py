"""Paired intervals (graf.reports.statistics) and per-spectrum records (graf.run.per_spectrum): the bootstrap
interval of a known paired difference covers it, the seed spread widens it, the verdicts follow the interval and
the metric's direction, mismatched test subsets are refused, and the records round-trip."""

from __future__ import annotations

import gzip

import numpy as np
import pytest

from graf.reports.statistics import PairingError, paired_difference, summary, verdict
from graf.run.per_spectrum import predictions_sha256, read_per_spectrum, write_per_spectrum


def _runs(values: np.ndarray, ids) -> list[dict]:
    return [dict(zip(ids, map(float, row))) for row in np.atleast_2d(values)]


def test_the_bootstrap_interval_of_a_known_paired_difference_covers_it():
    """120 spectra whose values vary a lot from spectrum to spectrum (scene difficulty) but whose paired
    difference is 0.5 dB plus small noise: the interval covers 0.5, is narrow (pairing removes the spectrum
    effect) and the verdict is ahead; the same data against itself is level with a zero-width interval."""
    rng = np.random.default_rng(0)
    ids = list(range(1000, 1120))
    base = rng.normal(20.0, 4.0, 120)
    ref = _runs(base, ids)
    method = _runs(base + 0.5 + rng.normal(0.0, 0.3, 120), ids)
    c = paired_difference(method, ref, "psnr")
    assert c["low"] < 0.5 < c["high"] and c["high"] - c["low"] < 0.25
    assert c["verdict"] == "ahead" and c["n_spectra"] == 120 and c["n_seeds"] == 1
    same = paired_difference(ref, ref, "psnr")
    assert same["diff"] == same["low"] == same["high"] == 0.0 and same["verdict"].startswith("level")


def test_coverage_over_repeated_draws_is_near_the_confidence_level():
    """Over 60 synthetic studies with a true difference of 0.2, the 95% interval covers it in most (a broken
    resampler that ignores the spread would cover it rarely)."""
    rng = np.random.default_rng(1)
    ids = list(range(120))
    covered = 0
    for _ in range(60):
        base = rng.normal(18.0, 3.0, 120)
        c = paired_difference(_runs(base + 0.2 + rng.normal(0, 1.0, 120), ids), _runs(base, ids), "psnr")
        covered += c["low"] <= 0.2 <= c["high"]
    assert covered >= 50


def test_seeds_widen_the_interval_to_include_each_seeds_difference():
    rng = np.random.default_rng(2)
    ids = list(range(150))
    base = rng.normal(20.0, 2.0, 150)
    seeds = np.stack([base + shift + rng.normal(0, 0.05, 150) for shift in (-0.4, 0.1, 0.9)])
    c = paired_difference(_runs(seeds, ids), _runs(base, ids), "psnr")
    assert c["n_seeds"] == 3 and len(c["seed_diffs"]) == 3
    assert c["low"] <= min(c["seed_diffs"]) and c["high"] >= max(c["seed_diffs"])
    assert c["boot_high"] - c["boot_low"] < c["high"] - c["low"]  # the spectra alone would claim more
    assert c["verdict"].startswith("level")  # one seed behind, one ahead: not settled
    s = summary(_runs(seeds, ids))
    assert s["seed_spread"] == pytest.approx(np.ptp(seeds.mean(axis=1))) and s["n_seeds"] == 3


def test_verdicts_follow_the_metrics_direction():
    assert verdict(0.1, 0.4, "psnr") == "ahead" and verdict(0.1, 0.4, "lpips") == "behind"
    assert verdict(-0.4, -0.1, "mse") == "ahead" and verdict(-0.4, -0.1, "ssim") == "behind"
    assert verdict(-0.1, 0.1, "psnr").startswith("level")


def test_different_test_subsets_are_refused():
    a = _runs(np.ones(5), [1, 2, 3, 4, 5])
    b = _runs(np.ones(5), [1, 2, 3, 4, 6])
    with pytest.raises(PairingError, match="missing ids \\[5\\]"):
        paired_difference(a, b, "psnr")


def test_per_spectrum_records_round_trip_and_predictions_hash_by_content(tmp_path):
    rows = [
        {
            "eval_scene": "conference_v2",
            "method": m,
            "id": i,
            "mse": 0.01 * i,
            "psnr": 20.0 + i / 3,
            "ssim": 0.7,
            "lpips": 0.2,
        }
        for m in ("graf", "knn")
        for i in (3, 1, 2)
    ]
    path = write_per_spectrum(tmp_path / "per_spectrum.csv.gz", rows)
    back = read_per_spectrum(path)
    assert [(r["method"], r["id"]) for r in back] == [(r["method"], r["id"]) for r in rows]
    for r, w in zip(back, rows):
        assert all(r[k] == pytest.approx(w[k], rel=1e-8) for k in ("mse", "psnr", "ssim", "lpips"))
    assert write_per_spectrum(tmp_path / "again.csv.gz", rows).read_bytes() == path.read_bytes()  # no time stamp
    pred = np.random.default_rng(0).random((3, 90, 360), dtype=np.float32)
    h = predictions_sha256({"ids": np.array([5, 6, 7]), "pred": pred})
    assert h == predictions_sha256({"ids": np.array([7, 5, 6]), "pred": pred[[2, 0, 1]]})  # batch order: same
    pred[1, 0, 0] += 1e-6
    assert h != predictions_sha256({"ids": np.array([5, 6, 7]), "pred": pred})
    (tmp_path / "bad.csv.gz").write_bytes(gzip.compress(b"eval_scene,method,id\nx,y,1\n"))
    with pytest.raises(ValueError, match="bad.csv.gz: not a per-spectrum record"):
        read_per_spectrum(tmp_path / "bad.csv.gz")


def test_a_baseline_tested_in_two_jobs_may_differ_by_float_rounding_only():
    from graf.reports.intervals import same_baseline

    ids = ["1", "2", "3"]
    a = {"psnr": dict(zip(ids, (22.5, 23.1, 21.0))), "ssim": dict(zip(ids, (0.8, 0.81, 0.79)))}
    gpu = {"psnr": {i: v + 3.8e-6 for i, v in a["psnr"].items()}, "ssim": dict(a["ssim"])}  # measured: GPU vs CPU
    assert same_baseline(a, gpu)
    assert not same_baseline(a, {"psnr": {**a["psnr"], "2": 23.11}, "ssim": a["ssim"]})  # 0.01 dB: another run
    assert not same_baseline(a, {"psnr": {"1": 22.5, "2": 23.1}, "ssim": {"1": 0.8, "2": 0.81}})  # another subset
