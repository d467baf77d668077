"""graf-bench's view of the machine while it measures: how much CPU other processes took (a row timed beside a
busy process is not a quiet measurement), how far repeated timings spread, and a competing process to start on
purpose (``bench.compete``: each row timed quiet, then beside it, side by side).

Load is read from ``/proc`` (Linux; :mod:`graf.machine`): the machine's busy CPU time (``/proc/stat``: user,
nice, system, irq, softirq, steal) minus this process's own (``/proc/self/stat``: user + system of all its
threads), over the phase's wall time, in cores; psutil where there is no ``/proc``; None where neither answers
or the phase was shorter than :data:`graf.machine.MIN_LOAD_WINDOW_S`.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from graf.machine import other_cores, reading

LOAD_LIMIT = 0.2  # cores other processes may use during a phase before its row is flagged
SPREAD_LIMIT = 0.15  # (max - min) / median of repeated timings before a row is flagged
# the competing process: a stream of short evaluations in one thread (what a second user's script does)
# (it ends itself when the bench is gone, however the bench ended)
COMPETITOR_CODE = (
    "import math, os\nparent = os.getppid()\nwhile os.getppid() == parent:\n    s = 0.0\n"
    "    for i in range(20000):\n        s += math.sin(i) * math.sqrt(i + 1.0)\n"
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
    """A competing single-threaded process (:data:`COMPETITOR_CODE`) for the ``with`` block; stopped after."""

    def __enter__(self):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        self.proc = subprocess.Popen([sys.executable, "-c", COMPETITOR_CODE], env=env)
        time.sleep(0.3)  # running before the clock starts
        return self

    def __exit__(self, *exc):
        self.proc.kill()
        self.proc.wait()
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
