"""The subprocess runner of the studies that start one graf command per point (graf-pareto, graf-curves)."""

from __future__ import annotations

import signal
import subprocess
import threading
from pathlib import Path

from graf.errors import Preempted


def run_command(cmd: list[str], folder: Path, env: dict, timeout: float) -> tuple[bool, str]:
    """Run one graf command into ``folder``, its output in ``folder/run.log``; ``(ok, last lines of its log)``.

    ``ok`` is true when the command exited 0 and wrote ``folder/results.json``; a command past ``timeout`` seconds
    is killed (not ok).  A SIGTERM to this process while the command runs is passed on to it (graf-train saves its
    state and writes ``preempted.json``); once it has stopped, :class:`graf.errors.Preempted` is raised, so the
    calling command stops with exit code 143 instead of going on to its next run, and the same command resumes.
    The SIGTERM handler before the call is put back after it."""
    folder.mkdir(parents=True, exist_ok=True)
    got = []
    with open(folder / "run.log", "w") as fh:
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env)

        def forward(signum, frame):
            got.append(signum)
            p.send_signal(signum)

        main = threading.current_thread() is threading.main_thread()  # only the main thread may set handlers
        previous = signal.signal(signal.SIGTERM, forward) if main else None
        try:
            try:
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        finally:
            if main:  # None: a handler set outside Python; the default stands in for it
                signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
    tail = "\n".join((folder / "run.log").read_text(errors="replace").splitlines()[-5:])
    if got:
        raise Preempted(
            f"SIGTERM: stopped while running into {folder} (exit code {p.returncode}); run the same "
            f"command again to resume\n{tail}"
        )
    return p.returncode == 0 and (folder / "results.json").exists(), tail
