"""The output folder, checked before Hydra writes anything into it: one that cannot be written (a file, a read-only
or full disk, a name too long) or that holds an interrupted training run ends the command with one line.

:class:`OutputFolderCheck` is a Hydra callback (``hydra.callbacks.output_folder``, every command): Hydra makes the
run's folder, opens its log and writes ``.hydra/`` before the command's own code runs, so a folder it cannot use
ended in Hydra's traceback, and a new run in the folder of an interrupted one (``checkpoints/last.ckpt``, no
``results.json``) overwrote that run's config and then its checkpoint.  A run that resumes that checkpoint
(graf-train with ``ckpt_path=`` inside the folder) is let in.  A folder another run is writing into is refused too:
each run holds a lock on its folder (:func:`lock_folder`, ``.graf-run.lock``) until it ends, so a second run into it
stops with one line instead of both finishing with only the later one's results left.
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
LOCK_NAME = ".graf-run.lock"  # in a run's (or a multirun's) folder while it runs: the holder's process id
_HELD: list[int] = []  # the lock files' descriptors this process holds, until it ends


def _ancestors() -> set[int]:
    """This process's parent, its parent's, ... (from /proc; empty where there is none)."""
    out, pid = set(), os.getpid()
    while pid > 1:
        try:
            with open(f"/proc/{pid}/stat") as f:
                pid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            break
        out.add(pid)
    return out


def lock_folder(folder: Path, create: bool = True) -> str | None:
    """Hold ``folder/.graf-run.lock`` (an exclusive ``flock``, released when this process ends, however it ends) and
    write this process's id into it; why not (None: held, or nothing to hold).  A lock held by a process this one
    descends from (a command that runs graf-train into its own folder) or a data-parallel rank other than 0 (they
    share rank 0's folder) takes nothing.  Where ``flock`` does not exist nothing is locked.  ``create=False``: only
    whether another run holds it, nothing written."""
    if any(os.environ.get(k, "0") not in ("", "0") for k in ("RANK", "LOCAL_RANK", "SLURM_PROCID")):
        return None
    try:
        import fcntl
    except ImportError:  # not a POSIX system
        return None
    path = folder / LOCK_NAME
    if not create and not path.is_file():
        return None
    fd = os.open(path, os.O_RDWR | (os.O_CREAT if create else 0), 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.read(fd, 32).decode(errors="replace").strip()
        os.close(fd)
        if holder.isdigit() and int(holder) in _ancestors() | {os.getpid()}:  # ours already, or an ancestor's
            return None
        return (
            f"another run (process {holder or '?'}) is writing into it ({path}): wait for it to end, or give this "
            "run another folder"
        )
    if not create:  # only asked whether another run holds it
        os.close(fd)  # (closing releases this process's flock on it)
        return None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _HELD.append(fd)
    return None


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
    ``hydra.sweep.dir``) cannot be written, (``resumable``: a single run) holds an interrupted run, or is another
    running command's (:func:`lock_folder`); else hold it for this command."""
    try:
        value = OmegaConf.select(config, key)
    except Exception:  # an interpolation only Hydra's run resolves: left to it
        return
    if value is None:
        return
    folder = Path(str(value))
    # another run's lock first (a run in progress also looks interrupted), then the folder's state, and only then
    # is anything written (a refused run leaves the folder as it was)
    why = folder_problem(folder) or lock_folder(folder, create=False)
    why = why or (interrupted_run(config, folder) if resumable else None) or lock_folder(folder)
    if why:
        fail(f"{key}={folder}: cannot be this run's output folder: {why}")


class OutputFolderCheck(Callback):
    """Hydra callback: :func:`check_output_folder` before a run (``hydra.run.dir``) or a multirun
    (``hydra.sweep.dir``) writes anything."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        check_output_folder(config, "hydra.run.dir", resumable=True)

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        check_output_folder(config, "hydra.sweep.dir", resumable=False)
