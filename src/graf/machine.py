"""What this machine's CPUs are doing: the busy CPU time of the whole machine and of this process (``/proc`` on
Linux, psutil elsewhere), and from them how many cores the *other* processes are using.  graf-bench records it
beside every timing (graf.studies.bench_load); GRaF's inference sizes its serial phases' threads by it
(graf.models.graf.inference)."""

from __future__ import annotations

import os
import threading
import time

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
MIN_LOAD_WINDOW_S = 0.25  # /proc counts CPU time in ticks of 10 ms: a shorter window's load is not measured


def cpu_seconds() -> tuple[float, float] | None:
    """``(busy CPU seconds of the whole machine, CPU seconds of this process)`` since boot / start; None where
    neither /proc nor psutil answers."""
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


def other_cores(since: tuple[float, tuple[float, float]], now: tuple[float, tuple[float, float]]) -> float | None:
    """Cores the other processes used between two ``(time.perf_counter(), cpu_seconds())`` readings; None when
    the window is shorter than :data:`MIN_LOAD_WINDOW_S` or a reading is missing."""
    (t0, c0), (t1, c1) = since, now
    if c0 is None or c1 is None or t1 - t0 < MIN_LOAD_WINDOW_S:
        return None
    return round(max(0.0, (c1[0] - c0[0]) - (c1[1] - c0[1])) / (t1 - t0), 3)


def reading() -> tuple[float, tuple[float, float] | None]:
    """``(time.perf_counter(), cpu_seconds())`` now."""
    return time.perf_counter(), cpu_seconds()


class LoadMonitor:
    """The other processes' load, kept fresh by a daemon thread that reads :func:`cpu_seconds` every
    ``interval`` seconds (two small files: nothing measurable); :meth:`other` is their cores over the last two
    intervals, None until then.  One per process (:func:`monitor`), started at first use."""

    def __init__(self, interval: float = 0.25):
        self.interval = float(interval)
        self.readings: list = []
        self._thread = threading.Thread(target=self._run, name="graf-load-monitor", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            self.readings = (self.readings + [reading()])[-3:]
            time.sleep(self.interval)

    def other(self) -> float | None:
        r = self.readings
        return other_cores(r[0], r[-1]) if len(r) >= 3 else None


_monitor: list = []
_monitor_lock = threading.Lock()


def monitor() -> LoadMonitor:
    with _monitor_lock:
        if not _monitor:
            _monitor.append(LoadMonitor())
    return _monitor[0]


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
