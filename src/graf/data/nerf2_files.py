"""The files of a NeRF2 scene folder, one reader each (:mod:`graf.data.nerf2_format` puts them together).

Every reader is strict: a problem raises :class:`DataFormatError` naming the file and what is wrong with it.

* ``spectrum/NNNNN.png``: :func:`scan_spectra` (ids from the names), :func:`read_spectrum_png` (one spectrum);
* ``train_index.txt`` / ``test_index.txt``: :func:`read_index`;
* ``tx_pos.csv``: :func:`read_positions` (the header and row rules of :mod:`graf.data.nerf2_format`);
* ``gateway_info.yml``: :func:`read_gateway`.
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from graf.data.spectrum_set import DataFormatError
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION

log = logging.getLogger(__name__)

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


def read_text(path: Path) -> str:
    """A text file decoded as UTF-8 with a leading byte-order mark stripped."""
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DataFormatError(path, f"is not UTF-8 text ({exc})") from None


def parse_id(text: str, where: str | Path) -> int:
    try:
        value = int(text.strip())
    except ValueError:
        raise DataFormatError(where, f"spectrum id {text.strip()!r} is not an integer") from None
    if value < 1:
        raise DataFormatError(where, f"spectrum id {value} is invalid: ids start at 1 (id k is tx_pos row k)")
    return value


def scan_spectra(spectrum_dir: Path) -> dict[int, Path]:
    if not spectrum_dir.is_dir():
        raise DataFormatError(spectrum_dir, "folder of spectrum PNGs is missing")
    files: dict[int, Path] = {}
    for f in sorted(spectrum_dir.iterdir()):
        if f.suffix.lower() != ".png":
            continue
        k = parse_id(f.stem, f)
        if k in files:
            raise DataFormatError(f, f"duplicate spectrum id {k}: also {files[k].name}")
        files[k] = f
    if not files:
        raise DataFormatError(spectrum_dir, "contains no .png spectra")
    return files


def read_index(path: Path) -> list[int]:
    ids: list[int] = []
    seen: set[int] = set()
    for line_no, line in enumerate(read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        k = parse_id(line, f"{path} line {line_no}")
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
    text = read_text(path).replace("\r\n", "\n").replace("\r", "\n")
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


def read_positions(path: Path) -> tuple[np.ndarray, bool]:
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


def read_gateway(path: Path) -> tuple[np.ndarray, np.ndarray]:
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
