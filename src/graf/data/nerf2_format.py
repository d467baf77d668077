"""Reader (and writer) for NeRF2's spatial-spectrum folder format.

Layout of a scene folder (XPengZhao/NeRF2, RFID spectrum datasets)::

    spectrum/NNNNN.png    8-bit grayscale, 90 rows (elevation) x 360 columns (azimuth), label = pixel / 255
    tx_pos.csv            optional header ``x,y,z``, then the k-th data row (data row k-1 counting from 0) is
                          the position of spectrum id k (ids start at 1)
    gateway_info.yml      gateway1.position [x, y, z]; gateway1.orientation quaternion (x, y, z, w)
    train_index.txt       spectrum ids, one per line (optional, together with test_index.txt)
    test_index.txt

Ids are parsed as integers, so ``00132.png`` and ``132.png`` are both id 132.

``tx_pos.csv`` is matched to ids by row number, so nothing may shift a row:

* UTF-8, a leading byte-order mark is stripped; LF, CRLF or CR line ends; blank lines are skipped, but a
  line of empty cells (``,,``) is a row and is refused as not numeric.
* The first row is a header only when its cells, stripped and lower-cased, are ``x``, ``y``, ``z`` in some
  order; columns are then taken by name (``z,y,x`` works).  A fully numeric first row is id 1's position
  (no header).  Any other first row (``NA,NA,NA``, ``x,y,w``, ``x,x,y``, ``1.0,2.0,abc``) is refused.
  Every data row must be 3 numbers.
* Row count: NeRF2 writes one row per spectrum, so the number of data rows must equal the largest
  spectrum id among the PNGs in ``spectrum/`` (not only the ids listed in the index files).  Fewer rows
  is refused; so is more, unless ``position_rows="at_least"`` (a slice whose ``tx_pos.csv`` holds the
  full dataset's rows), which accepts more rows with a warning.  A duplicated, missing or inserted row
  therefore fails the count instead of moving every later id onto the next row's position.  The counts
  are recorded in ``SpectrumSet.meta["position_rows"]``.
* The position of every listed id must be finite.

When *both* index files are missing, a seeded split is made (``split_seed``, ``train_fraction``; NeRF2
itself uses an unseeded 80/20 shuffle) and recorded in :attr:`SpectrumSet.split_source`.  Everything else
is strict: a problem raises :class:`DataFormatError` naming the file and what is wrong with it.  Constant
(e.g. all-zero) spectra are read but warned about (:func:`graf.data.spectrum_set.warn_flat_spectra`).
The reader of each file is in :mod:`graf.data.nerf2_files`.
"""

from __future__ import annotations

import io
import logging
import os
from pathlib import Path

import numpy as np
import torch
import yaml
from PIL import Image

from graf.data.nerf2_files import read_gateway, read_index, read_positions, read_spectrum_png, scan_spectra
from graf.data.spectrum_set import DataFormatError, SpectrumSet, warn_flat_spectra
from graf.geometry.grid import SPECTRUM_SHAPE
from graf.io import atomic_write_bytes

log = logging.getLogger(__name__)

# how the number of tx_pos.csv data rows must relate to the largest spectrum id (read_nerf2_folder)
POSITION_ROWS_RULES = ("exact", "at_least")
_ROW_RULE = (
    "data row k is the position of spectrum id k and NeRF2 writes one row per spectrum, so the row "
    "count must equal the largest id; a duplicated, missing or extra row would shift every later id's "
    "position"
)


def seeded_split(ids: list[int], seed: int, train_fraction: float) -> tuple[list[int], list[int]]:
    """Reproducible train/test split of ``ids`` (sorted first, then permuted by ``seed``)."""
    if not 0.0 < train_fraction < 1.0:
        raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")
    ordered = sorted(ids)
    perm = np.random.default_rng(seed).permutation(len(ordered))
    n_train = int(round(len(ordered) * train_fraction))
    n_train = min(max(n_train, 1), len(ordered) - 1)
    train = sorted(ordered[i] for i in perm[:n_train])
    test = sorted(ordered[i] for i in perm[n_train:])
    return train, test


def read_nerf2_folder(
    path: str | os.PathLike,
    *,
    name: str | None = None,
    frequency_hz: float = 915e6,
    split_seed: int = 0,
    train_fraction: float = 0.8,
    position_rows: str = "exact",
) -> SpectrumSet:
    """Read a scene in NeRF2's folder format (see the module docstring).

    ``position_rows``: ``"exact"`` (the format's rule) refuses a ``tx_pos.csv`` whose number of data rows is
    not the largest spectrum id in ``spectrum/``; ``"at_least"`` (a slice whose ``tx_pos.csv`` holds the
    full dataset's rows) also accepts more rows, with a warning.  Either way the counts are recorded in
    ``meta["position_rows"]``.
    """
    if position_rows not in POSITION_ROWS_RULES:
        raise DataFormatError(
            "position_rows",
            f"must be 'exact' or 'at_least' (data rows of tx_pos.csv = or >= the largest "
            f"spectrum id), got {position_rows!r}",
        )
    root = Path(path)
    if not root.is_dir():
        raise DataFormatError(root, "scene folder does not exist")
    files = scan_spectra(root / "spectrum")
    train_ids, test_ids, split_source = read_split(root, files, split_seed, train_fraction)
    positions_all, had_header = read_positions(root / "tx_pos.csv")
    gw_pos, gw_quat = read_gateway(root / "gateway_info.yml")
    all_ids = np.asarray(train_ids + test_ids, dtype=np.int64)
    positions = positions_of(root / "tx_pos.csv", positions_all, had_header, all_ids, files, position_rows)
    spectra = torch.empty((len(all_ids), *SPECTRUM_SHAPE), dtype=torch.float32)
    for i, k in enumerate(all_ids.tolist()):
        spectra[i] = torch.from_numpy(read_spectrum_png(files[k]))
    warn_flat_spectra(spectra, all_ids, root)
    n_train = len(train_ids)
    return SpectrumSet(
        name=name or root.name,
        spectra=spectra,
        positions=positions,
        ids=all_ids,
        train_idx=np.arange(n_train, dtype=np.int64),
        test_idx=np.arange(n_train, len(all_ids), dtype=np.int64),
        gateway_position=gw_pos,
        gateway_orientation=gw_quat,
        frequency_hz=float(frequency_hz),
        source=str(root),
        split_source=split_source,
        meta={
            "tx_pos_header": had_header,
            "unused_spectra": len(files) - len(all_ids),
            "position_rows": {"rows": len(positions_all), "largest_id": max(files), "rule": position_rows},
        },
    )


def read_split(
    root: Path, files: dict[int, Path], split_seed: int, train_fraction: float
) -> tuple[list[int], list[int], str]:
    """``(train ids, test ids, where the split comes from)``: the index files when both are there (disjoint, every
    id with its PNG in ``files``), else a seeded split of every spectrum (an error when only one is there)."""
    train_file, test_file = root / "train_index.txt", root / "test_index.txt"
    if train_file.is_file() and test_file.is_file():
        train_ids, test_ids = read_index(train_file), read_index(test_file)
        both = sorted(set(train_ids) & set(test_ids))
        if both:
            raise DataFormatError(test_file, f"ids also in {train_file.name}: {both[:10]}")
        for index_file, ids in ((train_file, train_ids), (test_file, test_ids)):
            missing = [k for k in ids if k not in files]
            if missing:
                raise DataFormatError(
                    index_file,
                    f"lists id {missing[0]} but spectrum/ has no PNG for it"
                    + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""),
                )
        split_source = f"index files {train_file.name} / {test_file.name}"
    elif train_file.is_file() or test_file.is_file():
        present, absent = (train_file, test_file) if train_file.is_file() else (test_file, train_file)
        raise DataFormatError(absent, f"is missing while {present.name} exists: give both index files or neither")
    else:
        if len(files) < 2:
            raise DataFormatError(
                root,
                f"{len(files)} spectrum and no index files: a seeded split needs at least 2 "
                "(one to train on, one to test)",
            )
        train_ids, test_ids = seeded_split(list(files), split_seed, train_fraction)
        split_source = f"seeded split (no index files): seed={split_seed}, train_fraction={train_fraction}"
        log.warning("%s: no index files; %s", root, split_source)
    for which, ids in (("training", train_ids), ("test", test_ids)):
        if not ids:  # index files listing no ids are refused above; this guards the seeded split
            raise DataFormatError(root, f"the {which} split is empty ({len(files)} spectra, {split_source})")
    return train_ids, test_ids, split_source


def positions_of(
    pos_file: Path,
    positions_all: np.ndarray,
    had_header: bool,
    ids: np.ndarray,
    files: dict[int, Path],
    position_rows: str,
) -> np.ndarray:
    """The positions ``[len(ids), 3]`` of ``ids`` (data row k is id k) in the rows ``positions_all`` of
    ``pos_file``, after the row-count rule (``position_rows``, against the largest id of the spectrum PNGs
    ``files``) and a check that each is finite."""
    rows = ids - 1
    if rows.max() >= len(positions_all):
        k = int(ids[rows.argmax()])
        note = " (not counting the header row)" if had_header else " (the file has no header row)"
        raise DataFormatError(
            pos_file, f"has {len(positions_all)} position rows but spectrum id {k} needs row {k}{note}; {_ROW_RULE}"
        )
    check_row_count(pos_file, len(positions_all), files, position_rows)
    positions = positions_all[rows]
    bad = ~np.isfinite(positions).all(axis=1)
    if bad.any():
        k = int(ids[np.argmax(bad)])
        raise DataFormatError(
            pos_file, f"position of spectrum id {k} (data row {k}) is not finite: {positions[np.argmax(bad)].tolist()}"
        )
    return positions


def check_row_count(pos_file: Path, n_rows: int, files: dict[int, Path], position_rows: str) -> None:
    """Refuse ``n_rows`` position rows other than the largest spectrum id of ``files`` (more are accepted, with a
    warning, under ``position_rows="at_least"``)."""
    largest = max(files)
    if n_rows == largest:
        return
    counts = f"has {n_rows} position rows but the largest spectrum id in spectrum/ is {largest} ({files[largest].name})"
    if n_rows < largest or position_rows == "exact":
        raise DataFormatError(
            pos_file,
            f"{counts}; {_ROW_RULE}"
            + (
                ". If this file holds a larger dataset's rows (a slice of it), read with position_rows='at_least'"
                if n_rows > largest
                else ""
            ),
        )
    extra = n_rows - largest
    log.warning(
        "%s %s: %d row%s more than the spectra need, accepted because position_rows='at_least' "
        "(rows 1..%d are taken as ids 1..%d; if a row was duplicated or inserted, every later id's "
        "position is WRONG)",
        pos_file,
        counts,
        extra,
        "" if extra == 1 else "s",
        largest,
        largest,
    )


def write_nerf2_folder(
    path: str | os.PathLike,
    spectra: np.ndarray | torch.Tensor,
    positions: np.ndarray,
    ids: np.ndarray,
    gateway_position: np.ndarray,
    gateway_orientation: np.ndarray,
    train_ids: np.ndarray | None = None,
    test_ids: np.ndarray | None = None,
) -> Path:
    """Write spectra ``[N, 90, 360]`` in [0, 1] as a NeRF2 folder that :func:`read_nerf2_folder` reads back.

    PNGs are quantised to 8 bits (pixel = round(255 * value)), as NeRF2 stores them.  ``tx_pos.csv`` gets
    a header and one row per id 1..max(id), so its row count is the largest id as the reader requires (rows
    of ids not written are zeros and never read); positions are written exactly (shortest round-trip repr).
    Write into a new or emptied folder: a PNG left there from an earlier write with a larger id would make
    the reader refuse the row count.
    """
    root = Path(path)
    (root / "spectrum").mkdir(parents=True, exist_ok=True)
    spectra = torch.as_tensor(spectra).detach().cpu().float().numpy()
    ids = np.asarray(ids, dtype=np.int64)
    if spectra.ndim != 3 or spectra.shape[1:] != SPECTRUM_SHAPE or len(spectra) != len(ids):
        raise ValueError(f"spectra must be [N, 90, 360] with N = len(ids) = {len(ids)}, got {tuple(spectra.shape)}")
    if not np.isfinite(spectra).all():
        raise ValueError("spectra contain non-finite values")
    positions = np.asarray(positions, dtype=np.float64)
    if positions.shape != (len(ids), 3) or not np.isfinite(positions).all():
        raise ValueError(f"positions must be finite [N, 3] with N = len(ids) = {len(ids)}, got {positions.shape}")
    if ids.min() < 1 or len(np.unique(ids)) != len(ids):
        raise ValueError("ids must be distinct integers >= 1 (id k is tx_pos.csv data row k)")
    width = max(5, len(str(int(ids.max()))))
    for k, s in zip(ids.tolist(), spectra):
        buf = io.BytesIO()
        Image.fromarray(np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8), mode="L").save(buf, format="PNG")
        atomic_write_bytes(root / "spectrum" / f"{k:0{width}d}.png", buf.getvalue())
    table = np.zeros((int(ids.max()), 3))  # one row per id 1..max(id), the reader's row-count rule
    table[ids - 1] = positions
    lines = ["x,y,z"] + [",".join(repr(float(v)) for v in row) for row in table]  # repr: exact round trip
    atomic_write_bytes(root / "tx_pos.csv", ("\n".join(lines) + "\n").encode())
    gw = {
        "gateway1": {
            "position": [float(v) for v in gateway_position],
            "orientation": [float(v) for v in gateway_orientation],
        }
    }
    atomic_write_bytes(root / "gateway_info.yml", yaml.safe_dump(gw).encode())
    if train_ids is not None and test_ids is not None:
        for fname, sel in (("train_index.txt", train_ids), ("test_index.txt", test_ids)):
            text = "".join(f"{int(k):0{width}d}\n" for k in sel)
            atomic_write_bytes(root / fname, text.encode())
    return root
