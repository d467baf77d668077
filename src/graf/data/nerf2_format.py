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
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
from pathlib import Path

import numpy as np
import torch
import yaml
from PIL import Image

from graf.data.spectrum_set import DataFormatError, SpectrumSet, warn_flat_spectra
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION, SPECTRUM_SHAPE
from graf.io import atomic_write_bytes

log = logging.getLogger(__name__)

# how the number of tx_pos.csv data rows must relate to the largest spectrum id (read_nerf2_folder)
POSITION_ROWS_RULES = ("exact", "at_least")
_ROW_RULE = (
    "data row k is the position of spectrum id k and NeRF2 writes one row per spectrum, so the row "
    "count must equal the largest id; a duplicated, missing or extra row would shift every later id's "
    "position"
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# leading bytes of formats that turn up under a .png name, to say what a refused file looks like
_OTHER_SIGNATURES = (
    (b"\xff\xd8\xff", "a JPEG file"),
    (b"GIF87a", "a GIF file"),
    (b"GIF89a", "a GIF file"),
    (b"BM", "a BMP file"),
    (b"II*\x00", "a TIFF file"),
    (b"MM\x00*", "a TIFF file"),
    (b"RIFF", "a RIFF (e.g. WebP) file"),
)


def _read_text(path: Path) -> str:
    """A text file decoded as UTF-8 with a leading byte-order mark stripped."""
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DataFormatError(path, f"is not UTF-8 text ({exc})") from None


def _parse_id(text: str, where: str | Path) -> int:
    try:
        value = int(text.strip())
    except ValueError:
        raise DataFormatError(where, f"spectrum id {text.strip()!r} is not an integer") from None
    if value < 1:
        raise DataFormatError(where, f"spectrum id {value} is invalid: ids start at 1 (id k is tx_pos row k)")
    return value


def _scan_spectra(spectrum_dir: Path) -> dict[int, Path]:
    if not spectrum_dir.is_dir():
        raise DataFormatError(spectrum_dir, "folder of spectrum PNGs is missing")
    files: dict[int, Path] = {}
    for f in sorted(spectrum_dir.iterdir()):
        if f.suffix.lower() != ".png":
            continue
        k = _parse_id(f.stem, f)
        if k in files:
            raise DataFormatError(f, f"duplicate spectrum id {k}: also {files[k].name}")
        files[k] = f
    if not files:
        raise DataFormatError(spectrum_dir, "contains no .png spectra")
    return files


def _read_index(path: Path) -> list[int]:
    ids: list[int] = []
    seen: set[int] = set()
    for line_no, line in enumerate(_read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        k = _parse_id(line, f"{path} line {line_no}")
        if k in seen:
            raise DataFormatError(path, f"duplicate id {k} at line {line_no}")
        seen.add(k)
        ids.append(k)
    if not ids:
        raise DataFormatError(path, "lists no ids")
    return ids


def read_spectrum_png(path: Path) -> np.ndarray:
    """One spectrum PNG as float32 ``[90, 360]`` in [0, 1] (pixel / 255).

    The file must start with the PNG signature: bytes of another format under a ``.png`` name are refused.
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(PNG_SIGNATURE))
    except OSError as exc:
        raise DataFormatError(path, f"cannot be read ({exc})") from None
    if head != PNG_SIGNATURE:
        if not head:
            what = "the file is empty"
        else:
            what = next((f"it is {name}" for sig, name in _OTHER_SIGNATURES if head.startswith(sig)), None)
            what = what or "not a PNG file"
            what += f" (signature {head!r}, expected {PNG_SIGNATURE!r})"
        raise DataFormatError(path, f"cannot be read as a PNG image: {what}")
    try:
        with Image.open(path, formats=["PNG"]) as im:
            mode, size = im.mode, im.size
            if mode != "L":
                raise DataFormatError(path, f"spectrum is not 8-bit grayscale (PIL mode {mode!r}, expected 'L')")
            if size != (N_AZIMUTH, N_ELEVATION):
                raise DataFormatError(
                    path, f"spectrum is {size[1]}x{size[0]} (rows x columns), expected {N_ELEVATION}x{N_AZIMUTH}"
                )
            arr = np.asarray(im, dtype=np.float32)
    except DataFormatError:
        raise
    except Exception as exc:  # truncated or corrupt PNG content
        raise DataFormatError(path, f"cannot be read as a PNG image ({exc})") from None
    return arr / 255.0


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


_XYZ = ("x", "y", "z")


def _header_problem(cells: list[str]) -> str | None:
    """None when ``cells`` name the columns x, y, z (each once, any order, any case, spaces around);
    otherwise what is wrong with them as a header."""
    if len(cells) != 3:
        return f"has {len(cells)} cells; expected 3 (x, y, z in any order)"
    names = [c.strip().lower() for c in cells]
    if sorted(names) == list(_XYZ):
        return None
    unknown = [c.strip() for c, n in zip(cells, names) if n not in _XYZ]
    repeated = sorted({n for n in names if n in _XYZ and names.count(n) > 1})
    missing = [n for n in _XYZ if n not in names]
    parts = []
    if unknown:
        parts.append(f"unknown name{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}")
    if repeated:
        parts.append(f"repeated {', '.join(map(repr, repeated))}")
    if missing:
        parts.append(f"missing {', '.join(map(repr, missing))}")
    return f"found names {[c.strip() for c in cells]!r} ({'; '.join(parts)}), expected x, y, z in any order"


def _csv_rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, cells) of each non-blank line of a CSV text file; a line of separators only (``,,``) is
    a row of empty cells, not a blank line, so it is never skipped (that would shift every later row)."""
    text = _read_text(path).replace("\r\n", "\n").replace("\r", "\n")
    out = []
    for line_no, line in enumerate(text.split("\n"), start=1):
        if not line.strip():
            continue
        try:
            cells = next(csv.reader([line]))
        except csv.Error as exc:
            raise DataFormatError(path, f"line {line_no} is not valid CSV ({exc}): {line!r}") from None
        out.append((line_no, cells))
    return out


def _read_positions(path: Path) -> tuple[np.ndarray, bool]:
    """Returns (rows [M, 3] as x, y, z, had_header).

    Decoded as UTF-8 with a byte-order mark stripped; LF, CRLF or CR line ends; blank lines are skipped.
    The first non-blank row is a header only when its cells, stripped and lower-cased, are x, y, z in some
    order, and columns are then taken by name (``z,y,x`` is read correctly).  A first row with no numeric
    cell that is not such a header (``NA,NA,NA``, ``x,y,w``) is refused, and so is one that is partly
    numeric; a fully numeric first row is the position of spectrum id 1 (no header).  Every other row must
    be 3 numbers.  So no spectrum is ever matched to the next row's position by a guess about line 1.
    """
    if not path.is_file():
        raise DataFormatError(path, "transmitter position file is missing")
    rows = _csv_rows(path)
    if not rows:
        raise DataFormatError(path, "is empty")
    first_no, first = rows[0]
    numeric = [_is_number(c) for c in first]
    if any(numeric) and not all(numeric):
        raise DataFormatError(
            path,
            f"line {first_no} {','.join(first)!r} is neither a header (no numeric cell) nor a numeric x,y,z "
            f"row: cells {[c for c, n in zip(first, numeric) if not n]!r} are not numbers, the others are",
        )
    had_header = not any(numeric)
    order = [0, 1, 2]  # column of x, y, z
    if had_header:
        problem = _header_problem(first)
        if problem is not None:
            raise DataFormatError(
                path,
                f"line {first_no} {','.join(first)!r} looks like a header (no numeric cell) but is not one: "
                f"{problem}; a header names the columns x, y, z, and a file without one starts with the "
                "numeric position of spectrum id 1",
            )
        names = [c.strip().lower() for c in first]
        order = [names.index(n) for n in _XYZ]
        rows = rows[1:]
    log.info(
        "%s: %s",
        path,
        f"header row {','.join(first)!r} found and skipped" if had_header else "no header row; first row is id 1",
    )
    out = np.full((len(rows), 3), np.nan)
    for i, (line_no, r) in enumerate(rows):
        if len(r) != 3:
            raise DataFormatError(path, f"line {line_no} has {len(r)} columns, expected 3 (x,y,z)")
        try:
            values = [float(c) for c in r]
        except ValueError:
            raise DataFormatError(path, f"line {line_no} is not numeric: {','.join(r)!r}") from None
        out[i] = [values[j] for j in order]
    return out, had_header


def _read_gateway(path: Path) -> tuple[np.ndarray, np.ndarray]:
    if not path.is_file():
        raise DataFormatError(path, "gateway file is missing")
    try:
        info = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise DataFormatError(path, f"is not valid YAML ({exc})") from None
    gw = info.get("gateway1") if isinstance(info, dict) else None
    if not isinstance(gw, dict):
        raise DataFormatError(path, "has no 'gateway1' section")
    values = {}
    for key, n in (("position", 3), ("orientation", 4)):
        if key not in gw or gw[key] is None:
            raise DataFormatError(path, f"gateway1 has no {key}")
        try:
            v = np.asarray(gw[key], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise DataFormatError(path, f"gateway1.{key} is not a list of numbers: {gw[key]!r}") from None
        if v.shape != (n,) or not np.all(np.isfinite(v)):
            raise DataFormatError(path, f"gateway1.{key} must be {n} finite numbers, got {gw[key]!r}")
        values[key] = v
    q = values["orientation"]
    # The norm as a correctly rounded sum (math.fsum), not np.linalg.norm: BLAS's dot product rounds differently
    # on other CPUs and numpy builds, and the normalised pose enters the scene's content fingerprint, which must
    # be the same on every machine (a checkpoint made on a CPU is resumed on a GPU machine).
    norm = math.sqrt(math.fsum(float(v) * float(v) for v in q))
    if not math.isclose(norm, 1.0, abs_tol=1e-3):
        raise DataFormatError(path, f"gateway1.orientation is not a unit quaternion (norm {norm:.4f})")
    return values["position"], q / norm


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
    files = _scan_spectra(root / "spectrum")
    train_file, test_file = root / "train_index.txt", root / "test_index.txt"
    if train_file.is_file() and test_file.is_file():
        train_ids, test_ids = _read_index(train_file), _read_index(test_file)
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

    positions_all, had_header = _read_positions(root / "tx_pos.csv")
    gw_pos, gw_quat = _read_gateway(root / "gateway_info.yml")

    all_ids = np.asarray(train_ids + test_ids, dtype=np.int64)
    pos_file = root / "tx_pos.csv"
    rows = all_ids - 1
    if rows.max() >= len(positions_all):
        k = int(all_ids[rows.argmax()])
        note = " (not counting the header row)" if had_header else " (the file has no header row)"
        raise DataFormatError(
            pos_file, f"has {len(positions_all)} position rows but spectrum id {k} needs row {k}{note}; {_ROW_RULE}"
        )
    n_rows, largest = len(positions_all), max(files)
    if n_rows != largest:
        counts = (
            f"has {n_rows} position rows but the largest spectrum id in spectrum/ is {largest} ({files[largest].name})"
        )
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
    positions = positions_all[rows]
    bad = ~np.isfinite(positions).all(axis=1)
    if bad.any():
        k = int(all_ids[np.argmax(bad)])
        raise DataFormatError(
            pos_file, f"position of spectrum id {k} (data row {k}) is not finite: {positions[np.argmax(bad)].tolist()}"
        )

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
            "position_rows": {"rows": n_rows, "largest_id": largest, "rule": position_rows},
        },
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
