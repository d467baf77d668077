"""A simulated dataset without its spectra, and the spectra rebuilt from it.

A catalog file stores each position's per-antenna channels ``h`` beside its uint8 spectrum, and the spectrum is a
function of ``h`` alone (the Bartlett amplitude over the 90 x 360 grid, min-max normalised, rounded to 1/255:
:class:`graf.sim.array.Bartlett`, :func:`graf.sim.array.to_uint8`).  ``slim`` writes the file without the
``spectra`` array (about 1 MB for 5,400 positions instead of about 67 MB), and ``restore`` writes the full file
again from it on any machine with torch and h5py, without a ray tracer: a way to carry the paper-density catalog
to a machine that cannot run Sionna RT (a lent GPU, say).

Rounding ties: float sums in another order (another thread count, another BLAS) move a value by about 1e-7, which
flips ``round(255 v)`` where ``255 v`` lies within that of a half (3 pixels of 175 million in a 5,400-position
layout, measured).  So ``slim`` also stores the original value of every pixel whose rebuilt ``255 v`` is within
``TIE`` of a half (``tie_index``, ``tie_value``; a few hundred thousand), and of any other pixel the rebuild gets
wrong; ``restore`` puts them back.  The result is the traced file's spectra bit for bit wherever the rebuild is
within ``TIE`` of the original computation.  ``slim`` records the original spectra's sha256 (``spectra_sha256``)
and ``restore`` the rebuilt ones', so a caller can check the two match (``tests/sim/test_sim_slim.py``).

    python -m graf.sim.slim slim data/sim/conference_v1/2.4ghz.h5 conference_v1.slim.h5
    python -m graf.sim.slim restore conference_v1.slim.h5 data/sim/conference_v1/2.4ghz.h5
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import h5py
import numpy as np
import torch

from graf.data.spectrum_set import DataFormatError
from graf.geometry.grid import SPECTRUM_SHAPE
from graf.sim.array import Bartlett, to_uint8

CHUNK = 256  # positions per Bartlett call
TIE = 1e-3  # pixels whose 255 v is this close to a half are stored as they were traced


def spectra_sha256(spectra: np.ndarray) -> str:
    """sha256 of a uint8 ``[N, 90, 360]`` array's C-order bytes."""
    return hashlib.sha256(np.ascontiguousarray(spectra, dtype=np.uint8).tobytes()).hexdigest()


def rebuild_spectra(
    channels: np.ndarray, antenna_positions: np.ndarray, wavelength: float
) -> tuple[np.ndarray, np.ndarray]:
    """uint8 spectra ``[N, 90, 360]`` from channels ``[N, K]`` (on the CPU, as the simulator computes them), and the
    flat indices of their pixels within ``TIE`` of a rounding tie."""
    bartlett = Bartlett(np.asarray(antenna_positions, np.float64), float(wavelength))
    h = torch.from_numpy(np.asarray(channels, np.complex64))
    out, ties = [], []
    for i in range(0, len(h), CHUNK):
        v = bartlett.spectra(h[i : i + CHUNK])
        out.append(to_uint8(v))
        scaled = v.clamp(0, 1).numpy().astype(np.float64) * 255
        near = np.abs(scaled - np.floor(scaled) - 0.5) < TIE
        ties.append(np.flatnonzero(near) + i * v[0].numel())
    return np.concatenate(out), np.concatenate(ties).astype(np.int64)


def _copy(src: h5py.File, dst: h5py.File, skip: tuple[str, ...]) -> None:
    for key in src:
        if key not in skip:
            dst.create_dataset(key, data=src[key][()], track_times=False)
    for k, v in src.attrs.items():
        dst.attrs[k] = v


def slim(src: str | Path, dst: str | Path) -> str:
    """Write ``src`` without its spectra to ``dst`` (atomically); the spectra's sha256, also stored in ``dst``."""
    src, dst = Path(src), Path(dst)
    with h5py.File(src, "r") as f:
        for key in ("spectra", "channels", "antenna_positions"):
            if key not in f:
                raise DataFormatError(src, f"has no '{key}' dataset: not a simulated catalog file")
        if "wavelength" not in f.attrs:
            raise DataFormatError(src, "has no 'wavelength' attribute")
        original = f["spectra"][()]
        digest = spectra_sha256(original)
        rebuilt, ties = rebuild_spectra(f["channels"][()], f["antenna_positions"][()], float(f.attrs["wavelength"]))
        keep = np.union1d(ties, np.flatnonzero(rebuilt.ravel() != original.ravel()))
        tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
        dst.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(tmp, "w", track_order=False) as g:
            _copy(f, g, skip=("spectra",))
            kw = dict(compression="gzip", compression_opts=9, shuffle=True, track_times=False)
            g.create_dataset("tie_index", data=np.diff(keep, prepend=0).astype(np.uint32), **kw)  # delta-coded
            g.create_dataset("tie_value", data=original.ravel()[keep], **kw)
            g.attrs["spectra_sha256"] = digest
    tmp.replace(dst)
    return digest


def restore(src: str | Path, dst: str | Path) -> dict:
    """Write the full dataset file ``dst`` from a slim file ``src`` (atomically); ``{n, sha256, expected, match}``."""
    src, dst = Path(src), Path(dst)
    with h5py.File(src, "r") as f:
        for key in ("channels", "antenna_positions"):
            if key not in f:
                raise DataFormatError(src, f"has no '{key}' dataset: not a slim catalog file")
        if "wavelength" not in f.attrs:
            raise DataFormatError(src, "has no 'wavelength' attribute")
        spectra, _ = rebuild_spectra(f["channels"][()], f["antenna_positions"][()], float(f.attrs["wavelength"]))
        if "tie_index" in f:
            flat = spectra.reshape(-1)
            flat[np.cumsum(f["tie_index"][()].astype(np.int64))] = f["tie_value"][()]
        expected = f.attrs.get("spectra_sha256")
        digest = spectra_sha256(spectra)
        tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
        dst.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(tmp, "w", track_order=False) as g:
            g.create_dataset(
                "spectra",
                data=spectra,
                chunks=(min(64, len(spectra)), *SPECTRUM_SHAPE),
                compression="gzip",
                compression_opts=4,
                shuffle=True,
                track_times=False,
            )
            _copy(f, g, skip=("spectra", "tie_index", "tie_value"))
            g.attrs["spectra_sha256"] = digest
    tmp.replace(dst)
    expected = None if expected is None else str(expected)
    return {"n": len(spectra), "sha256": digest, "expected": expected, "match": expected == digest}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 3 or args[0] not in ("slim", "restore"):
        print(__doc__.strip().splitlines()[-2:][0].strip(), file=sys.stderr)
        print("usage: python -m graf.sim.slim {slim|restore} SRC DST", file=sys.stderr)
        return 2
    if args[0] == "slim":
        print(f"{args[2]}: spectra sha256 {slim(args[1], args[2])}")
        return 0
    r = restore(args[1], args[2])
    print(
        f"{args[2]}: {r['n']} spectra rebuilt, sha256 {r['sha256']} ({'matches' if r['match'] else 'DIFFERS from'} "
        f"the original {r['expected']})"
    )
    return 0 if r["match"] else 1


if __name__ == "__main__":
    sys.exit(main())
