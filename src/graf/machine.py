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
    """``(busy CPU seconds of the whole machine, CPU seconds of this process and its descendants)`` since boot /
    start; None where neither /proc nor psutil answers."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
        busy = fields[0] + fields[1] + fields[2] + sum(fields[5:8])  # user nice system (idle iowait) irq softirq steal
        return busy / _TICK, own_ticks(os.getpid()) / _TICK
    except (OSError, ValueError, IndexError):
        try:
            import psutil  # where there is no /proc

            t = psutil.cpu_times()
            p = psutil.Process().cpu_times()
            return t.user + t.system + getattr(t, "nice", 0.0), p.user + p.system
        except Exception:
            return None


def _stat(pid: int) -> list[str]:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()


def _children(pid: int) -> list[int]:
    out = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                out += [int(c) for c in f.read().split()]
    except OSError:  # gone, or a kernel without the children files: its children are not told apart
        pass
    return out


def own_ticks(pid: int) -> int:
    """CPU ticks of process ``pid`` and of its descendants, live (``/proc/<pid>/task/*/children``) and finished
    (``cutime``, ``cstime``): a compile it runs (GRaF's kernels are built at first use) or its data-loading workers
    are its own work, not another process's load."""
    stat = _stat(pid)
    total = sum(int(x) for x in stat[11:15])  # utime stime cutime cstime (fields 14-17)
    for child in _children(pid):
        try:
            total += own_ticks(child)
        except (OSError, ValueError, IndexError):  # a child that ended between the listing and the read
            pass
    return total


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
    ``interval`` seconds (two small files and this process's children: nothing measurable); :meth:`other` is their
    cores, measured from CPU time (never guessed from the load average), None until two windows are read.  One per
    process (:func:`monitor`), started at first use."""

    def __init__(self, interval: float = 0.25):
        self.interval = float(interval)
        self.readings: list = []
        self._thread = threading.Thread(target=self._run, name="graf-load-monitor", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            self.readings = (self.readings + [reading()])[-5:]
            time.sleep(self.interval)

    def other(self) -> float | None:
        """The other processes' cores in the *quieter* of the last two windows of two intervals each (0.5 s): a
        load that has just ended (a burst of CPU work, an install's compile) reads as quiet at once, and only a
        load that lasted both windows lowers anything.  None until the first window is read."""
        r = self.readings
        if len(r) < 3:
            return None
        loads = [
            x for x in (other_cores(r[-3], r[-1]), other_cores(r[0], r[2]) if len(r) == 5 else None) if x is not None
        ]
        return min(loads) if loads else None

    def window_s(self) -> float:
        """The seconds :meth:`other` looked back over."""
        r = self.readings
        return r[-1][0] - r[0][0] if len(r) >= 2 else 0.0


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


BUSY_CORES = 0.5  # other processes' load (cores) from which a run leaves cores to them


def threads_beside_load(threads: int) -> tuple[int, float | None]:
    """``(threads to run on, other processes' cores)``: ``threads`` on a quiet machine (other processes below
    :data:`BUSY_CORES`, measured by :func:`monitor`), else ``threads`` less the cores they use (rounded), at least 1.
    Beside a busy process, torch's intra-op threads wait at every operation for the one that shares its core: the
    main job ran 3.4x faster on 1 thread than on 2 beside one busy process (0.53 against 1.86 steps/s, 2026-12-05)."""
    other = monitor().other()
    if other is None or other < BUSY_CORES:
        return threads, other
    return max(1, min(threads, round(available_cores() - other))), other
