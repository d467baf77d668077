"""Synthesis at new positions: the Python call and graf-synthesize."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from graf.bands import Band
from graf.case_studies.synthesis import synthesize
from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector
from graf.data.nerf2_format import read_nerf2_folder
from graf.data.scenes import NeRF2Scene
from graf.models.knn import KNNModule


def _dm(L=4):
    return SpectrumDataModule(
        NeRF2Scene("rfid_s23", "embedded:rfid_s23_200"),
        Band("915mhz", 915e6),
        NeighborSelector(L=L, L_train=(L, L), radius=10.0),
        batch_size=8,
    )


def test_synthesis_at_test_positions_equals_evaluation_predictions():
    dm = _dm()
    dm.setup()
    model = KNNModule()
    test_pos = dm.positions[dm.test_rows].numpy()
    synth = synthesize(model, dm, test_pos)
    batch = next(iter(dm.test_dataloader()))
    expected = model.predict_spectra(batch)
    torch.testing.assert_close(synth[: len(expected)], expected.clamp(0, 1))
    assert synth.shape == (40, 90, 360)


def test_synthesis_rejects_bad_positions():
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        synthesize(KNNModule(), _dm(), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="finite"):
        synthesize(KNNModule(), _dm(), np.full((1, 3), np.nan))


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_graf_synthesize_writes_a_nerf2_folder(tmp_path):
    csv = tmp_path / "new.csv"
    csv.write_text("0.0,-0.5,1.0\n-0.1,-0.3,0.95\n0.05,0.0,1.02\n")  # no header
    out = tmp_path / "synth"
    p = subprocess.run(
        [
            str(Path(sys.executable).parent / "graf-synthesize"),
            "model=knn",
            f"positions={csv}",
            f"out={out}",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    d = read_nerf2_folder(out, frequency_hz=915e6)
    assert d.spectra.shape == (3, 90, 360) and sorted(d.ids.tolist()) == [1, 2, 3]
    np.testing.assert_allclose(d.positions[np.argsort(d.ids)], np.loadtxt(csv, delimiter=","), atol=1e-6)
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z\n0,0\n")
    p = subprocess.run(
        [
            str(Path(sys.executable).parent / "graf-synthesize"),
            "model=knn",
            f"positions={bad}",
            f"hydra.run.dir={tmp_path / 'run2'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode != 0 and "bad.csv: line 2 has 2 columns" in p.stderr
