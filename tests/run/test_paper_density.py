"""The studies' records at the paper's density: a seeded test subset that depends on its own seed only (the same
for every method, training seed and L), per-spectrum records whose ids are that subset and whose means are the
run's figures, and learning-rate schedules that follow the run's steps and are recorded."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector
from graf.data.scene_rows import seeded_subset
from graf.data.scenes import NeRF2Scene
from graf.run.per_spectrum import read_per_spectrum
from graf.run.train import train
from tests.models.test_graf_model import UHF


def _dm(path, seed=0, L=3, subset=6, subset_seed=0):
    dm = SpectrumDataModule(
        NeRF2Scene(name="tiny", path=str(path)),
        UHF,
        NeighborSelector(L=L, L_train=(1, L), radius=10.0),
        seed=seed,
        test_subset=subset,
        test_subset_seed=subset_seed,
    )
    dm.setup()
    return dm


def test_the_test_subset_depends_on_its_own_seed_only(make_scene):
    path = make_scene(n=48)
    ids = {(s, L): _dm(path, seed=s, L=L).split_summary()["test_ids"] for s in (0, 1, 2) for L in (1, 3, 5)}
    first = next(iter(ids.values()))
    assert len(first) == 6 and all(v == first for v in ids.values())
    assert _dm(path, subset_seed=1).split_summary()["test_ids"] != first
    assert _dm(path, subset=None).split_summary()["n_test"] == 12  # null: the whole test split
    rows = np.arange(100, 112)
    assert np.array_equal(seeded_subset(rows, 50, 0, "x"), rows) and list(seeded_subset(rows, 4, 0, "x")) == sorted(
        seeded_subset(rows, 4, 0, "x")
    )


def _knn_dl_run(compose_cfg, folder, *extra):
    """graf-train's config of KNN-DL on a tiny NeRF2-format scene at 915 MHz, plus ``extra`` overrides."""
    base = ("scene=nerf2", f"scene.nerf2.path={folder}", "band=915mhz", "model=knn_dl", "data.batch_size=2")
    return compose_cfg("train", (*base, "plot_count=0", *extra))


def test_a_run_writes_per_spectrum_records_of_its_test_subset_and_its_schedule(compose_cfg, make_scene, tmp_path):
    train(_knn_dl_run(compose_cfg, make_scene(n=32), "data.test_subset=5", "trainer.max_steps=3"))
    out = tmp_path / "out"
    result = json.loads((out / "results.json").read_text())
    rows = read_per_spectrum(out / result["per_spectrum"])
    test_ids = result["splits"]["test_ids"]
    assert len(test_ids) == 5 and result["n_test"] == 5
    for method in ("knn-dl", "knn"):
        mine = [r for r in rows if r["method"] == method]
        assert sorted(r["id"] for r in mine) == sorted(test_ids)
        figures = result["metrics"] if method == "knn-dl" else result["baselines"]["knn"]["metrics"]
        for k in ("mse", "psnr", "ssim", "lpips"):
            assert np.mean([r[k] for r in mine]) == pytest.approx(figures[f"test/{k}"], rel=1e-5, abs=1e-6)
    hashes = result["prediction_sha256"][result["eval_scene"]]
    assert set(hashes) == {"knn-dl", "knn"} and all(len(h) == 64 for h in hashes.values())
    s = result["schedule"]
    assert s["kind"] == "exponential" and s["length_steps"] == 3 and s["run_steps"] == 3
    assert s["lr_end"] == pytest.approx(s["lr_start"] * 0.1)


def test_a_schedule_much_longer_than_the_run_is_kept_and_warned_about(compose_cfg, make_scene, caplog):
    cfg = _knn_dl_run(compose_cfg, make_scene(n=24), "trainer.max_steps=2", "model.decay_steps=1000", "baselines=null")
    with caplog.at_level(logging.WARNING, logger="graf"):
        _, run = train(cfg)
    assert run.record.schedule["length_steps"] == 1000
    assert any("model.decay_steps=1000 is 500x this run's 2 steps" in r.getMessage() for r in caplog.records)
