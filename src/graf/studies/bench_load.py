"""graf-bench's view of the machine while it measures: how much CPU other processes took (a row timed beside a
busy process is not a quiet measurement), how far repeated timings spread, and a competing process to start on
purpose (``bench.compete``: each row timed quiet, then beside it, side by side).

Load is read from ``/proc`` (Linux): the machine's busy CPU time (``/proc/stat``: user, nice, system, irq,
softirq, steal) minus this process's own (``/proc/self/stat``: user + system of all its threads), over the
phase's wall time, in cores; psutil where there is no ``/proc``; None where neither answers.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

LOAD_LIMIT = 0.2  # cores other processes may use during a phase before its row is flagged
SPREAD_LIMIT = 0.15  # (max - min) / median of repeated timings before a row is flagged
MIN_LOAD_WINDOW_S = 0.25  # /proc counts CPU time in ticks of 10 ms: a shorter phase's load is not measured (None)
# the competing process: a stream of short evaluations in one thread (what a second user's script does)
# (it ends itself when the bench is gone, however the bench ended)
COMPETITOR_CODE = (
    "import math, os\nparent = os.getppid()\nwhile os.getppid() == parent:\n    s = 0.0\n"
    "    for i in range(20000):\n        s += math.sin(i) * math.sqrt(i + 1.0)\n"
)
_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_seconds() -> tuple[float, float] | None:
    """``(busy CPU seconds of the whole machine, CPU seconds of this process)`` since boot / start."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
        busy = fields[0] + fields[1] + fields[2] + sum(fields[5:8])  # user nice system (idle iowait) irq softirq steal
        with open("/proc/self/stat") as f:
            stat = f.read().rsplit(")", 1)[1].split()
        own = int(stat[11]) + int(stat[12])  # utime stime (fields 14, 15)
        return busy / _TICK, own / _TICK
    except (OSError, ValueError, IndexError):
        try:
            import psutil  # where there is no /proc

            t = psutil.cpu_times()
            p = psutil.Process().cpu_times()
            return t.user + t.system + getattr(t, "nice", 0.0), p.user + p.system
        except Exception:
            return None


class LoadMeter:
    """Cores other processes used during the ``with`` block (``.cores``; None where it cannot be read, or the block
    was shorter than :data:`MIN_LOAD_WINDOW_S`)."""

    def __init__(self):
        self.cores: float | None = None

    def __enter__(self):
        self._t, self._cpu = time.perf_counter(), cpu_seconds()
        return self

    def __exit__(self, *exc):
        end, wall = cpu_seconds(), time.perf_counter() - self._t
        if self._cpu is not None and end is not None and wall >= MIN_LOAD_WINDOW_S:
            self.cores = round(max(0.0, (end[0] - self._cpu[0]) - (end[1] - self._cpu[1])) / wall, 3)
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
