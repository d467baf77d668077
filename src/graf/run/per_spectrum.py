"""Per-spectrum records of a run's evaluations: every test spectrum's MSE, PSNR, SSIM and LPIPS (the values the
test loop averaged into ``test/...``), for the model and each baseline on each test scene, beside
``results.json`` as ``per_spectrum.csv.gz``::

    eval_scene,method,id,mse,psnr,ssim,lpips
    conference_v2,graf-ray-weights,17,0.00412,23.85,0.712,0.231

and a content hash of each evaluation's predictions (:func:`predictions_sha256`, in ``results.json``
``prediction_sha256``), so that any comparison can be recomputed from the records (paired by ``id``) and any two
runs checked for identity without keeping the arrays.  The file is gzip with no time stamp: the same figures
give the same bytes.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import io
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from graf.callbacks import PER_SPECTRUM
from graf.io import atomic_write_bytes

PER_SPECTRUM_FILE = "per_spectrum.csv.gz"
COLUMNS = ("eval_scene", "method", "id", *PER_SPECTRUM)


def predictions_sha256(arrays: dict) -> str:
    """sha256 of an evaluation's predictions: the ids (int64, little-endian) then the predicted spectra (float32,
    little-endian, C order), both in id order (the same predictions in any batch order give the same hash)."""
    ids = np.asarray(arrays["ids"], dtype="<i8")
    order = np.argsort(ids, kind="stable")
    h = hashlib.sha256()
    h.update(ids[order].tobytes())
    h.update(np.ascontiguousarray(np.asarray(arrays["pred"], dtype="<f4")[order]).tobytes())
    return h.hexdigest()


def evaluation_rows(eval_scene: str, method: str, arrays: dict) -> list[dict]:
    """One row per test spectrum of an evaluation (``arrays``: a :class:`graf.callbacks.PredictionCollector`'s,
    with ``metric_<name>``); none where its per-spectrum metrics were not collected."""
    cols = [f"metric_{k}" for k in PER_SPECTRUM]
    if not all(c in arrays for c in cols):
        return []
    ids = np.asarray(arrays["ids"])
    return [
        {
            "eval_scene": eval_scene,
            "method": method,
            "id": int(i),
            **{k: float(arrays[c][j]) for k, c in zip(PER_SPECTRUM, cols)},
        }
        for j, i in enumerate(ids)
    ]


def write_per_spectrum(path: str | Path, rows: Iterable[dict]) -> Path:
    """``rows`` as a gzipped CSV (:data:`COLUMNS`; floats with 9 significant digits), written atomically."""
    text = io.StringIO()
    w = csv.writer(text, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow([r["eval_scene"], r["method"], int(r["id"]), *(format(float(r[k]), ".9g") for k in PER_SPECTRUM)])
    return atomic_write_bytes(path, gzip.compress(text.getvalue().encode(), mtime=0))


def read_per_spectrum(path: str | Path) -> list[dict]:
    """The rows of a per-spectrum file (ids as int, metrics as float); a clear error naming the file when a
    column is missing or a value is not a number."""
    path = Path(path)
    with gzip.open(path, "rt", newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: not a per-spectrum record (missing columns {missing})")
        rows = []
        for n, r in enumerate(reader, start=2):
            try:
                rows.append(
                    {
                        "eval_scene": r["eval_scene"],
                        "method": r["method"],
                        "id": int(r["id"]),
                        **{k: float(r[k]) for k in PER_SPECTRUM},
                    }
                )
            except ValueError as exc:
                raise ValueError(f"{path}, line {n}: {exc}") from None
    return rows
