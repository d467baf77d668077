"""A catalog file without its spectra, and the spectra rebuilt from its channels (graf.sim.slim)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from graf.data.spectrum_set import DataFormatError
from graf.sim.array import Bartlett, array_positions, to_uint8
from graf.sim.dataset import read_dataset
from graf.sim.slim import main, restore, slim, spectra_sha256
from graf.sim.tracer import spectra_from_paths

WAVELENGTH = 0.1243


def _catalog(path, n=40, seed=0):
    """A catalog-shaped file whose spectra come the simulator's way: random traced paths -> channels -> spectra."""
    rng = np.random.default_rng(seed)
    antennas = array_positions(WAVELENGTH)
    bartlett = Bartlett(antennas, WAVELENGTH)
    P = 6
    gains = torch.from_numpy(rng.normal(size=(n, P)) + 1j * rng.normal(size=(n, P)))
    gains[0] = 0  # a position no path reached: all-zero spectrum
    d = rng.normal(size=(n, P, 3))
    d[..., 2] = np.abs(d[..., 2])
    dirs = torch.from_numpy(d / np.linalg.norm(d, axis=-1, keepdims=True))
    h, spectra = spectra_from_paths(bartlett, gains, dirs, "cos")
    with h5py.File(path, "w") as f:
        f.create_dataset("spectra", data=to_uint8(spectra), compression="gzip")
        f.create_dataset("channels", data=h.numpy())
        f.create_dataset("positions", data=rng.uniform(0, 5, size=(n, 3)))
        f.create_dataset("ids", data=np.arange(1, n + 1, dtype=np.int64))
        f.create_dataset("num_paths", data=np.full(n, P, np.int32))
        f.create_dataset("train_idx", data=np.arange(0, n - 8, dtype=np.int64))
        f.create_dataset("test_idx", data=np.arange(n - 8, n, dtype=np.int64))
        f.create_dataset("antenna_positions", data=antennas)
        a = f.attrs
        a["scene"], a["band"], a["wavelength"], a["frequency_hz"] = "toy", "2.4ghz", WAVELENGTH, 2.412e9
        a["gateway_position"], a["gateway_orientation"] = np.zeros(3), np.array([0, 0, 0, 1.0])
        a["bounds"], a["config"] = np.array([[0.0, 0, 0], [5, 5, 3]]), "{}"
    return path


def test_slim_then_restore_gives_the_same_file_contents(tmp_path):
    src = _catalog(tmp_path / "full.h5")
    digest = slim(src, tmp_path / "slim.h5")
    with h5py.File(tmp_path / "slim.h5") as f:
        assert "spectra" not in f and f.attrs["spectra_sha256"] == digest
    r = restore(tmp_path / "slim.h5", tmp_path / "back.h5")
    assert r == {"n": 40, "sha256": digest, "expected": digest, "match": True}
    a, b = read_dataset(src), read_dataset(tmp_path / "back.h5")
    assert torch.equal(a.spectra, b.spectra)  # bit for bit, the all-zero spectrum included
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.test_idx, b.test_idx)
    with h5py.File(src) as f, h5py.File(tmp_path / "back.h5") as g:
        assert spectra_sha256(f["spectra"][()]) == g.attrs["spectra_sha256"]
        assert {k: str(v) for k, v in f.attrs.items()} == {
            k: str(v) for k, v in g.attrs.items() if k != "spectra_sha256"
        }


def test_pixels_the_rebuild_rounds_otherwise_come_back_as_traced(tmp_path):
    """Another machine's float sums can flip round(255 v) at a tie: slim keeps those pixels (and any the rebuild
    gets wrong) as traced, so restore returns the traced spectra exactly."""
    src = _catalog(tmp_path / "full.h5")
    with h5py.File(src, "a") as f:
        s = f["spectra"][()]
        s[5, 10, 20] = (int(s[5, 10, 20]) + 1) % 256  # as if traced where the rebuild rounds the other way
        s[7, 0, 0] = (int(s[7, 0, 0]) + 100) % 256
        f["spectra"][...] = s
    digest = slim(src, tmp_path / "slim.h5")
    with h5py.File(tmp_path / "slim.h5") as f:
        assert 2 <= len(f["tie_index"]) < 40 * 90 * 360 // 100  # the changed pixels and the near-ties, no more
    r = restore(tmp_path / "slim.h5", tmp_path / "back.h5")
    assert r["match"] and r["sha256"] == digest
    assert torch.equal(read_dataset(src).spectra, read_dataset(tmp_path / "back.h5").spectra)


def test_restore_reports_rebuilt_spectra_that_differ(tmp_path, capsys):
    slim(_catalog(tmp_path / "full.h5"), tmp_path / "slim.h5")
    with h5py.File(tmp_path / "slim.h5", "a") as f:
        f["channels"][3] = f["channels"][4]  # a changed channel: the rebuilt spectra are not the traced ones
    assert main(["restore", str(tmp_path / "slim.h5"), str(tmp_path / "back.h5")]) == 1
    assert "DIFFERS" in capsys.readouterr().out


def test_a_file_without_channels_is_named_in_the_error(tmp_path):
    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f.create_dataset("spectra", data=np.zeros((2, 90, 360), np.uint8))
    with pytest.raises(DataFormatError, match="bad.h5.*channels"):
        slim(tmp_path / "bad.h5", tmp_path / "out.h5")
    with pytest.raises(DataFormatError, match="bad.h5.*channels"):
        restore(tmp_path / "bad.h5", tmp_path / "out.h5")
    assert not (tmp_path / "out.h5").exists()
