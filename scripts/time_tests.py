"""Time the README's test command (the default tests: ``pytest -m "not slow" -n 2``) in this checkout and record it,
so that the README's figure for it is generated from a timed run, never typed:

    python scripts/time_tests.py [--out sweeps/test_timing/results.json]
    python scripts/time_tests.py --from-log CI_LOG --commit SHA    # the default tests of a `bash .ci/run` log

``--from-log`` records the default tests of a log of ``bash .ci/run`` (or of the command above) run on this machine
instead: their seconds as pytest's closing line gives them (the first such line: the default tests), the commit that
ran them, and no load reading. Writes (atomically) the wall seconds, pytest's closing counts, the commit, the date
and the machine (CPU model and cores from /proc/cpuinfo, and how busy the other processes kept it while the tests
ran: a figure taken beside other work says so). Run it in a fresh clone, after ``bash scripts/setup.sh``, with
nothing else running; ``python scripts/headline.py`` then writes the README's sentence from the record. Exits with
pytest's code.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

from graf.io import atomic_write_json
from graf.machine import other_cores, reading

ROOT = Path(__file__).resolve().parents[1]
COMMAND = ["-m", "pytest", "-m", "not slow", "-n", "2"]  # the README's test command, after the interpreter
CLOSING = re.compile(r"=+ (?P<counts>.*?) in (?P<seconds>[\d.]+)s")


def cpu_model() -> str:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    found = re.search(r"^model name\s*:\s*(.+)$", text, re.M)
    return found.group(1).strip() if found else platform.machine()


def from_log(log: Path, commit: str | None, out: str) -> int:
    """The record of the default tests whose output is in ``log`` (the first pytest closing line)."""
    found = CLOSING.search(log.read_text(errors="replace"))
    if found is None or not commit:
        print(f"error: {log}: no pytest closing line, or no --commit given", file=sys.stderr)
        return 2
    record = {
        "command": "python " + " ".join(c if " " not in c else f'"{c}"' for c in COMMAND) + f" (in {log.name})",
        "exit_code": 0 if " failed" not in found["counts"] else 1,
        "wall_s": round(float(found["seconds"]), 1),
        "pytest_closing": found["counts"],
        "commit": commit,
        "date": datetime.datetime.fromtimestamp(log.stat().st_mtime, datetime.timezone.utc).strftime("%Y-%m-%d"),
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count()},
        "other_load_cores": None,  # not read: the log's run measured no load
    }
    atomic_write_json(out, record)
    print(f"{out}: {record['wall_s']} s, {record['pytest_closing']}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "sweeps" / "test_timing" / "results.json"))
    ap.add_argument("--from-log", default=None, help="a log of bash .ci/run: record its default tests' timing")
    ap.add_argument("--commit", default=None, help="with --from-log: the commit the log's run tested")
    args = ap.parse_args()
    if args.from_log:
        return from_log(Path(args.from_log), args.commit, args.out)
    start, t0 = reading(), time.perf_counter()
    p = subprocess.run([sys.executable, *COMMAND], cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    sys.stdout.write(p.stdout[-4000:])
    sys.stderr.write(p.stderr[-2000:])
    closing = [m.groupdict() for m in CLOSING.finditer(p.stdout)]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    record = {
        "command": "python " + " ".join(c if " " not in c else f'"{c}"' for c in COMMAND),
        "exit_code": p.returncode,
        "wall_s": round(wall, 1),
        "pytest_closing": closing[-1]["counts"] if closing else None,
        "commit": commit.stdout.strip() or None,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count()},
        # the tests' own workers are this process's children (graf.machine.own_ticks): what is left is other work
        "other_load_cores": other_cores(start, reading()),
    }
    atomic_write_json(args.out, record)
    print(f"{args.out}: {record['wall_s']} s, {record['pytest_closing']}")
    return p.returncode


if __name__ == "__main__":
    sys.exit(main())
