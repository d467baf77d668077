"""Checks of a simulated dataset file: it opens, its arrays agree, and it was made with the settings asked for.

A dataset file is found by scene, band and number of positions alone (:meth:`graf.sim.scene.SimulatedScene.
dataset_path`), so everything else that shapes its spectra is compared with what the file records (its
``config`` attribute, the generating configuration every file has carried since the first format): the scene's
geometry, objects and their materials, gateway, transmitter region, count, seeds and split, array, tracing
settings, the band's frequency and the number of positions, and for ``graf-simulate`` the chunk size too (the
chunks batch the sources Sionna RT traces together, which changes the spectra).  The scene's name and
description shape nothing and are not compared.  A difference is refused in one line naming each differing
setting with its value in the file and the asked one (:func:`compare_config`): a changed setting never reads, or
skips tracing over, a dataset made by other settings.  Files written before these checks record every setting
compared (the recorded configuration has not changed since the simulator's first version), so they read as
before when their settings are asked for.  A setting the asked configuration has and a file does not record (a
key added to the scene configs later) is compared with the value files made before it used, when
:data:`RECORDED_SINCE` gives it; otherwise it is a difference ("absent in the file"): what the file was made
with is unknown.

Every read also checks the arrays (:func:`check_arrays`, in the style of the NeRF2 folder readers): as many ids,
positions and path counts as spectra, distinct ids from 1, and a split of rows inside the file, neither part empty,
no row twice, none in both.  A file HDF5 cannot open (truncated by a copy that stopped short, say) is refused
as unreadable (:func:`open_dataset`), one whose compressed spectra cannot be read as damaged
(:func:`read_spectra`), and either is left where it is: only its owner deletes it.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from graf.data.spectrum_set import DataFormatError
from graf.geometry.grid import SPECTRUM_SHAPE

DATASETS = ("spectra", "positions", "ids", "train_idx", "test_idx")
ATTRIBUTES = ("gateway_position", "gateway_orientation", "frequency_hz", "bounds", "config")
UNSHAPING = {("scene", "name"), ("scene", "description")}  # free text and the folder's name: no spectrum changes
# A setting added to the configs after files were written (none yet): where -> the value those files were made
# with, compared in its place when a file does not record it.  Without an entry such a file is refused.
RECORDED_SINCE: dict[tuple, object] = {}
REMAKE = "delete it, or trace it again with graf-simulate ... sim.overwrite=true"
_ABSENT = object()


def open_dataset(path: Path) -> h5py.File:
    """The file opened for reading; one that HDF5 cannot open is refused as unreadable (never deleted)."""
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        what = "truncated (a copy or a disk that stopped short)" if "truncated" in str(exc) else "truncated or not HDF5"
        raise DataFormatError(
            path,
            f"is unreadable: HDF5 cannot open it ({exc}); the file is {what}: {REMAKE}",
        ) from None


def read_spectra(path: Path, f: h5py.File) -> np.ndarray:
    """Every spectrum of the file; a damaged compressed chunk is refused in one line."""
    try:
        return f["spectra"][()]
    except OSError as exc:
        raise DataFormatError(path, f"is damaged: its spectra cannot be read ({exc}); {REMAKE}") from None


def check_arrays(path: Path, f: h5py.File) -> int:
    """Refuse a file whose datasets or attributes are missing or disagree (see the module doc); returns its
    number of spectra.  Reads the small arrays only."""
    for key in DATASETS:
        if key not in f:
            raise DataFormatError(path, f"has no '{key}' dataset")
    for key in ATTRIBUTES:
        if key not in f.attrs:
            raise DataFormatError(path, f"has no '{key}' attribute (graf-simulate writes it)")
    s = f["spectra"]
    if len(s.shape) != 3 or s.shape[1:] != SPECTRUM_SHAPE or s.dtype != np.uint8:
        raise DataFormatError(path, f"spectra must be uint8 [N, 90, 360], got {s.dtype} {s.shape}")
    n = int(s.shape[0])
    if n < 2:
        what = f"{n} spectr{'um' if n == 1 else 'a'}"
        raise DataFormatError(path, f"holds {what}; a dataset needs at least 2 (one to train on, one to test)")
    for key, what, tail in (("ids", "ids", ()), ("positions", "positions", (3,)), ("num_paths", "path counts", ())):
        if key in f and (len(f[key].shape) != 1 + len(tail) or f[key].shape[1:] != tail or f[key].shape[0] != n):
            shape = list(f[key].shape)
            raise DataFormatError(path, f"has {n} spectra but {shape[0] if shape else 0} {what} (shape {shape})")
    ids = f["ids"][()]
    if ids.dtype.kind not in "iu" or ids.min() < 1:
        raise DataFormatError(path, f"ids must be integers from 1 (id k is row k-1, as NeRF2), got {ids[:5].tolist()}")
    values, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise DataFormatError(path, f"spectrum id {values[counts > 1][0]} appears {counts.max()} times in 'ids'")
    train = check_index(path, f, "train_idx", n)
    test = check_index(path, f, "test_idx", n)
    both = np.intersect1d(train, test)
    if both.size:
        more = f" (and {both.size - 10} more)" if both.size > 10 else ""
        raise DataFormatError(path, f"rows {both[:10].tolist()}{more} are in both train_idx and test_idx")
    return n


def check_index(path: Path, f: h5py.File, key: str, n: int) -> np.ndarray:
    """The rows of the split ``key``: integers in 0..n-1, each once, at least one."""
    rows = f[key][()]
    if rows.ndim != 1 or (rows.size and rows.dtype.kind not in "iu"):
        raise DataFormatError(path, f"{key} must be a list of integer rows, got {rows.dtype} {list(rows.shape)}")
    if not rows.size:
        raise DataFormatError(path, f"{key} is empty: no spectrum to {'train' if key == 'train_idx' else 'test'} on")
    bad = rows[(rows < 0) | (rows >= n)]
    if bad.size:
        raise DataFormatError(path, f"{key} holds row {int(bad[0])}, but the file has {n} spectra (rows 0-{n - 1})")
    values, counts = np.unique(rows, return_counts=True)
    if (counts > 1).any():
        c = int(counts.max())
        raise DataFormatError(
            path, f"{key} lists row {int(values[counts > 1][0])} {'twice' if c == 2 else f'{c} times'}"
        )
    return rows.astype(np.int64)


def stored_config(path: Path, f: h5py.File) -> dict:
    """The generating configuration the file records (its ``config`` attribute)."""
    try:
        config = json.loads(f.attrs["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(path, f"its 'config' attribute is not the JSON graf-simulate writes ({exc})") from None
    if not isinstance(config, dict):
        raise DataFormatError(path, f"its 'config' attribute holds a {type(config).__name__}, not a mapping")
    return config


def compare_config(path: Path, stored: dict, asked: dict, scene_key: str, remedy: str) -> None:
    """Refuse a file whose recorded configuration ``stored`` differs from ``asked`` (the dataset's configuration,
    :func:`graf.sim.dataset.dataset_config` or part of it: only its top-level keys are compared) in any setting that
    shapes the dataset: one line naming each, its value in the file and the asked one, then ``remedy``."""
    asked = json.loads(json.dumps(asked, sort_keys=True, default=str))  # as the file stores it: lists, no tuples
    found: list[str] = []
    for key in sorted(asked):
        _differences(stored.get(key, RECORDED_SINCE.get((key,), _ABSENT)), asked[key], (key,), found, scene_key)
    if found:
        raise DataFormatError(path, f"was made with other settings than asked: {'; '.join(found)}; {remedy}")


def _differences(stored, asked, where: tuple, found: list[str], scene_key: str) -> None:
    if where in UNSHAPING:
        return
    if isinstance(stored, dict) and isinstance(asked, dict):
        for k in sorted(set(stored) | set(asked)):
            old = stored.get(k, RECORDED_SINCE.get((*where, k), _ABSENT))
            _differences(old, asked.get(k, _ABSENT), (*where, k), found, scene_key)
    elif stored is _ABSENT or asked is _ABSENT or stored != asked:
        found.append(f"{setting_name(where, scene_key)}: {_shown(stored)} in the file, {_shown(asked)} asked")


def setting_name(where: tuple, scene_key: str) -> str:
    """A compared setting as a user sets it: ``scene.<scene>.gateway.position``, ``sim.chunk_size``."""
    head, *rest = where
    if head == "scene":
        return ".".join(("scene", scene_key, *rest))
    if head == "num_tx":
        return "the number of positions (num_tx)"
    if head == "chunk_size":
        return "sim.chunk_size"
    return ".".join(where)


def _shown(value) -> str:
    if value is _ABSENT:
        return "absent"
    return repr(value) if isinstance(value, str) else json.dumps(value, sort_keys=True)
