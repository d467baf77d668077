"""Atomic file writes: a file either appears whole or not at all (temp file + os.replace)."""

from __future__ import annotations

import errno
import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from graf.errors import ConfigError, WriteError


def writable_dir(path: str | os.PathLike, setting: str) -> Path:
    """``path`` made if missing and checked writable (a probe file is made and removed), or a
    :class:`graf.errors.ConfigError` naming ``setting`` and the reason: before a long job writes into it."""

    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=path, prefix=".graf-write-probe.")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ConfigError(f"{setting}={path}: cannot write there ({exc.strerror or exc})") from None
    return path


# what the place written to lacks (not a bug of graf's): a write failing so ends the command with one line
NOT_WRITABLE = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENAMETOOLONG)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``path`` whole or not at all: a failed write leaves the file that was there.  A disk that is full or
    read-only raises :class:`graf.errors.WriteError` naming the file."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno in NOT_WRITABLE:
            raise WriteError(f"{path}: cannot be written ({exc.strerror or exc})") from None
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | os.PathLike, obj) -> Path:
    return atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=False, default=str) + "\n").encode())


def atomic_write_npz(path: str | os.PathLike, **arrays: np.ndarray) -> Path:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def is_rank_zero() -> bool:
    """Whether this process writes a run's files: always, except in the ranks other than 0 of a data-parallel
    run (torch.distributed initialised), which compute the same figures and write nothing."""
    import torch.distributed as dist  # lazy: graf.io (atomic writes) is used by code that needs no torch

    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0
