"""The output folder, checked before Hydra writes anything into it: one that cannot be written (a file, a read-only
or full disk, a name too long) or that holds an interrupted training run ends the command with one line.

:class:`OutputFolderCheck` is a Hydra callback (``hydra.callbacks.output_folder``, every command): Hydra makes the
run's folder, opens its log and writes ``.hydra/`` before the command's own code runs, so a folder it cannot use
ended in Hydra's traceback, and a new run in the folder of an interrupted one (``checkpoints/last.ckpt``, no
``results.json``) overwrote that run's config and then its checkpoint.  A run that resumes that checkpoint
(graf-train with ``ckpt_path=`` inside the folder) is let in.
"""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from graf.app.command import fail

NAME_MAX = 255  # the longest file name most file systems take (bytes)


def folder_problem(folder: Path) -> str | None:
    """Why a command cannot write its files into ``folder`` (None: it can).  The folder is made if missing and a
    probe file is written into it and removed."""
    try:
        if folder.exists() and not folder.is_dir():
            return "it is a file, not a folder"
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".graf-write-probe.")
        try:
            os.write(fd, b"0")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        return os_problem(folder, exc)
    return None


def os_problem(folder: Path, exc: OSError) -> str:
    """An OSError met while making or writing ``folder``, in words."""
    code = exc.errno
    if code == errno.ENAMETOOLONG:
        longest = max(folder.parts, key=lambda p: len(os.fsencode(p)))
        return (
            f"a name in its path is {len(os.fsencode(longest))} bytes long, longer than the file system takes "
            f"(at most {NAME_MAX} a name)"
        )
    if code in (errno.ENOTDIR, errno.EEXIST):
        above = next((p for p in [folder, *folder.parents] if p.exists() and not p.is_dir()), None)
        return f"{above} is a file, not a folder" if above else (exc.strerror or str(exc))
    if code == errno.EROFS:
        return "it is on a read-only file system"
    if code in (errno.EACCES, errno.EPERM):
        return "it cannot be written (permission denied)"
    if code in (errno.ENOSPC, errno.EDQUOT):
        return f"no space is left on its disk ({exc.strerror or 'ENOSPC'})"
    return exc.strerror or str(exc)


def is_inside(path, folder: Path) -> bool:
    return bool(path) and folder.resolve() in Path(str(path)).resolve().parents


def interrupted_run(config: DictConfig, folder: Path) -> str | None:
    """Why this run must not start in ``folder``: it holds an interrupted training run (``checkpoints/last.ckpt``
    and no ``results.json``), which this run does not resume (None: it may start)."""
    last = folder / "checkpoints" / "last.ckpt"
    if not last.is_file() or (folder / "results.json").is_file():
        return None
    ckpt = OmegaConf.select(config, "ckpt_path", default=None, throw_on_resolution_failure=False)
    # graf-train (Hydra's job name, whatever task_name an experiment sets) resuming a checkpoint of this folder
    if OmegaConf.select(config, "hydra.job.name", default=None) == "train" and is_inside(ckpt, folder):
        return None
    return (
        f"it holds an interrupted training run ({last}, no results.json) that this run would overwrite: resume it "
        f"(its graf-train command with ckpt_path={last}) or choose another folder"
    )


def check_output_folder(config: DictConfig, key: str, resumable: bool) -> None:
    """End the command with one line (exit code 2) when the folder at ``key`` (``hydra.run.dir``,
    ``hydra.sweep.dir``) cannot be written, or (``resumable``: a single run) holds an interrupted run."""
    try:
        value = OmegaConf.select(config, key)
    except Exception:  # an interpolation only Hydra's run resolves: left to it
        return
    if value is None:
        return
    folder = Path(str(value))
    why = folder_problem(folder) or (interrupted_run(config, folder) if resumable else None)
    if why:
        fail(f"{key}={folder}: cannot be this run's output folder: {why}")


class OutputFolderCheck(Callback):
    """Hydra callback: :func:`check_output_folder` before a run (``hydra.run.dir``) or a multirun
    (``hydra.sweep.dir``) writes anything."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        check_output_folder(config, "hydra.run.dir", resumable=True)

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        check_output_folder(config, "hydra.sweep.dir", resumable=False)
