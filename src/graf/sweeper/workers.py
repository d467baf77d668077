"""Who runs a study's trials: the further worker processes ``n_jobs`` starts (the same command again on the same
storage, :func:`graf.app.launch.again`), and each trial's owner (host, pid and process start time), which tells a
live worker from a dead one on this host."""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
from pathlib import Path

import psutil

from graf.app.launch import again
from graf.sweeper.trials import quote

log = logging.getLogger("graf")
SET_BY_THE_SWEEPER = (
    "hydra.sweep.dir=",
    "hydra.sweeper.worker_rank=",
    "hydra.sweeper.storage=",
    "hydra.sweeper.study_name=",
)


def _process_start(pid: int) -> float | None:
    try:
        return float(psutil.Process(pid).create_time())
    except Exception:
        return None


def this_owner() -> dict:
    return {"host": socket.gethostname(), "pid": os.getpid(), "start": _process_start(os.getpid())}


def owner_alive(owner: dict | None) -> bool | None:
    """Whether a trial's owning process still runs (None: it ran on another host; unknown)."""
    if not owner:
        return False
    if owner.get("host") != socket.gethostname():
        return None
    start = _process_start(int(owner["pid"]))
    if start is None:
        return False
    return owner.get("start") is None or abs(start - float(owner["start"])) < 1.0


def start_workers(n_jobs: int, threads: int, sweep_dir: Path, url: str, name: str) -> list[subprocess.Popen]:
    """``n_jobs - 1`` more processes of this command on the same storage (rank 1..n-1), ``threads`` torch
    threads each; each writes ``worker_<rank>.log`` in the sweep folder."""
    procs = []
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    argv = [a for a in sys.argv[1:] if not a.startswith(SET_BY_THE_SWEEPER)]
    for rank in range(1, n_jobs):
        cmd = again(
            *argv,
            f"hydra.sweep.dir={quote(str(sweep_dir))}",
            f"hydra.sweeper.storage={quote(url)}",
            f"hydra.sweeper.study_name={quote(name)}",
            f"hydra.sweeper.worker_rank={rank}",
        )
        f = open(sweep_dir / f"worker_{rank}.log", "ab")
        procs.append(subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env))
        log.info("worker %d started (pid %d): log %s", rank, procs[-1].pid, f.name)
    return procs
