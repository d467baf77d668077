"""The bands study's intervals: one test scene at several test bands makes one cell per band (KNN differs between
them), and a model trained at another band is compared with the one trained at the test band, on the same spectra
(seed E.5's question)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from graf.reports.intervals import write_intervals
from graf.run.per_spectrum import write_per_spectrum

BANDS = {"1.8ghz": 1.8e9, "2.4ghz": 2.412e9}
IDS = list(range(300, 420))


def _bands_study(root, cross_band_loss: float) -> dict:
    """A GRaF trained at each band, each tested at each band (seed 0); KNN beside it.  The model trained at the
    other band scores ``cross_band_loss`` dB below the in-band one on every spectrum, plus noise."""
    rng = np.random.default_rng(1)
    truth = {b: rng.normal(20.0, 3.0, len(IDS)) for b in BANDS}  # the in-band model's PSNR per test band
    knn = {b: truth[b] - 0.4 for b in BANDS}
    for train, train_hz in BANDS.items():
        for test, test_hz in BANDS.items():
            noise = rng.normal(0.0, 0.2, len(IDS))
            psnr = truth[test] - (0.0 if train == test else cross_band_loss) + noise - noise.mean()
            folder = root / f"band={train},eval_band={test}"
            folder.mkdir(parents=True)
            rows = [
                {"eval_scene": "conference_v1", "method": m, "id": i, "mse": 10 ** (-v / 10), "psnr": v}
                | {"ssim": 0.5, "lpips": 0.3}
                for m, values in (("graf", psnr), ("knn", knn[test]))
                for i, v in zip(IDS, values)
            ]
            write_per_spectrum(folder / "per_spectrum.csv.gz", rows)
            result = {
                "method": "graf",
                "scene": "conference_v1",
                "train_scenes": ["conference_v1"],
                "train_bands_hz": [train_hz],
                "band_hz": test_hz,
                "metrics": {"test/psnr": 0.0},
                "config": {"seed": 0, "sim_num_tx": None, "neighbors": {"L": 10}},
                "per_spectrum": "per_spectrum.csv.gz",
                "evaluations": [{"eval_scene": "conference_v1", "band_hz": test_hz, "metrics": {}, "baselines": {}}],
            }
            (folder / "results.json").write_text(json.dumps(result))
    return truth


def test_each_test_band_is_its_own_cell_with_its_own_knn(tmp_path):
    _bands_study(tmp_path / "runs", cross_band_loss=1.0)
    rows = write_intervals(tmp_path / "runs", tmp_path)
    psnr = [r for r in rows if r["metric"] == "psnr"]
    assert {(r["train_band"], r["eval_band"]) for r in psnr} == {
        (a, b) for a in ("1.8 GHz", "2.412 GHz") for b in ("1.8 GHz", "2.412 GHz")
    }
    in_band = [r for r in psnr if r["train_band"] == r["eval_band"]]
    assert all(r["vs_knn"]["diff"] == pytest.approx(0.4, abs=0.1) for r in in_band)


@pytest.mark.parametrize("loss", [1.0, 0.0])
def test_a_model_trained_at_another_band_is_compared_with_the_in_band_one(tmp_path, loss):
    _bands_study(tmp_path / "runs", cross_band_loss=loss)
    write_intervals(tmp_path / "runs", tmp_path)
    record = json.loads((tmp_path / "intervals.json").read_text())
    transfers = [c for c in record["band_transfers"] if c["metric"] == "psnr"]
    assert {(c["train_band"], c["eval_band"]) for c in transfers} == {
        ("1.8 GHz", "2.412 GHz"),
        ("2.412 GHz", "1.8 GHz"),
    }
    for c in transfers:
        assert c["low"] <= -loss <= c["high"]  # the interval covers the known loss
        assert c["n_spectra"] == len(IDS)
        assert c["verdict"].split(" ")[0] == ("behind" if loss else "level")
    assert "trained at another band" in (tmp_path / "intervals.md").read_text()


@pytest.mark.parametrize(("loss", "verdict"), [(1.0, "holds"), (0.0, "not reproduced"), (-1.0, "refuted")])
def test_the_ledger_judges_the_band_claim_from_the_transfers(tmp_path, loss, verdict):
    """The E.5 row of the real claims config, read from a synthetic bands record: a known loss across bands holds,
    none is not reproduced, a gain refutes it; the platform column names each transfer."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from graf.app.config import CONF_DIR
    from graf.reports.claims import judge

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        claims = OmegaConf.to_container(compose("claims").claims, resolve=True)
    claim = {c["id"]: c for c in claims}["e5_bands"] | {"method": "graf"}
    record = tmp_path / claim["record"]
    record.parent.mkdir(parents=True)
    _bands_study(tmp_path / "runs", cross_band_loss=loss)
    write_intervals(tmp_path / "runs", record.parent)
    row = judge(claim, tmp_path)
    assert row["verdict"] == verdict
    assert "1.8 GHz -> 2.412 GHz: " in row["platform"] and "2.412 GHz -> 1.8 GHz: " in row["platform"]
    assert row["interval"].count("[") == 2


def test_a_band_claim_with_an_unknown_direction_is_a_clear_error(tmp_path):
    from graf.errors import ConfigError
    from graf.reports.claims import judge

    _bands_study(tmp_path / "runs", cross_band_loss=1.0)
    write_intervals(tmp_path / "runs", tmp_path)
    claim = {"id": "e5", "kind": "transfer", "record": "intervals.json", "method": "graf", "metric": "psnr"}
    with pytest.raises(ConfigError, match="'e5': expect must be 'ahead' or 'behind', got 'worse'"):
        judge(claim | {"expect": "worse"}, tmp_path)
    assert judge(claim, tmp_path)["verdict"] == "holds"  # behind, the default
