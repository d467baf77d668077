"""graf-bench's view of the machine while it measures: how much CPU other processes took (a row timed beside a
busy process is not a quiet measurement), how far repeated timings spread, and a competing process to start on
purpose (``bench.compete``: each row timed quiet, then beside it, side by side).

Load is read from ``/proc`` (Linux; :mod:`graf.machine`): the machine's busy CPU time (``/proc/stat``: user, nice,
system, irq, softirq, steal) minus this process's own (``/proc/self/stat``: user + system of all its threads, and of
its children: :func:`graf.machine.own_ticks`), over the phase's wall time, in cores; psutil where there is no
``/proc``; None where neither answers or the phase was shorter than :data:`graf.machine.MIN_LOAD_WINDOW_S`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from graf.machine import other_cores, reading

LOAD_LIMIT = 0.2  # cores other processes may use during a phase before its row is flagged
SPREAD_LIMIT = 0.15  # (max - min) / median of repeated timings before a row is flagged
# the competing process: a stream of short evaluations in one thread (what a second user's script does); it ends
# itself when the bench (its first argument, a pid) is gone, however the bench ended
COMPETITOR_CODE = (
    "import math, os, sys\nbench = int(sys.argv[1])\ndef alive():\n    try:\n        os.kill(bench, 0)\n"
    "        return True\n    except OSError:\n        return False\nwhile alive():\n    s = 0.0\n"
    "    for i in range(20000):\n        s += math.sin(i) * math.sqrt(i + 1.0)\n"
)
# started through a launcher that exits at once, so the competitor is no descendant of the bench: the load monitor
# counts a process's own children as its own work (graf.machine.own_ticks), and a competitor is another user's
LAUNCHER_CODE = (
    "import subprocess, sys\np = subprocess.Popen([sys.executable, '-c', sys.argv[1], sys.argv[2]], "
    "start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\nprint(p.pid)\n"
)


class LoadMeter:
    """Cores other processes used during the ``with`` block (``.cores``; None where it cannot be read, or the block
    was shorter than :data:`MIN_LOAD_WINDOW_S`: /proc's 10 ms ticks)."""

    def __init__(self):
        self.cores: float | None = None

    def __enter__(self):
        self._start = reading()
        return self

    def __exit__(self, *exc):
        self.cores = other_cores(self._start, reading())
        return False


class Competitor:
    """A competing single-threaded process (:data:`COMPETITOR_CODE`) for the ``with`` block, not a descendant of
    this one (another user's process); stopped after."""

    def __enter__(self):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        out = subprocess.run(
            [sys.executable, "-c", LAUNCHER_CODE, COMPETITOR_CODE, str(os.getpid())],
            env=env, capture_output=True, text=True, check=True, timeout=60,
        )  # fmt: skip
        self.pid = int(out.stdout.split()[-1])
        time.sleep(0.3)  # running before the clock starts
        return self

    def __exit__(self, *exc):
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            return False
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and _running(self.pid):  # gone, or a zombie its new parent has not reaped
            time.sleep(0.02)
        return False


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def spread(times: list[float]) -> float | None:
    """``(max - min) / median`` of repeated timings; None for fewer than two."""
    if len(times) < 2:
        return None
    s = sorted(times)
    return round((s[-1] - s[0]) / s[len(s) // 2], 4)


def disturbances(row: dict, phases: tuple[str, ...] = ("infer", "train")) -> list[str]:
    """Why a row's quiet timings cannot be trusted: other processes' load or the spread of its repeats."""
    out = []
    for phase in phases:
        load, sp = row.get(f"{phase}_load_cores"), row.get(f"{phase}_spread")
        if load is not None and load > LOAD_LIMIT:
            out.append(f"{phase}: other processes used {load:.2f} cores (limit {LOAD_LIMIT})")
        if sp is not None and sp > SPREAD_LIMIT:
            out.append(f"{phase}: repeated timings spread {sp:.0%} (limit {SPREAD_LIMIT:.0%})")
    return out
