#!/usr/bin/env bash
# Time the README's first command as a newcomer runs it: a fresh clone of this repository's HEAD, an empty home
# folder (no pip cache, no compiled kernel, no LPIPS weights), nothing else running.  Times the set-up
# (`bash scripts/setup.sh`) and the main job (`.venv/bin/graf-train experiment=graf_rfid_s23`) separately and writes
# the record sweeps/newcomer_timing/{results.json, timing.md}, from which the README, Home and Getting started say
# how long they take (python scripts/headline.py; the pages include timing.md).
#   bash scripts/time_newcomer.sh [OUT]        (OUT: the record's folder, default sweeps/newcomer_timing)
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
OUT=${1:-$REPO/sweeps/newcomer_timing}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
git clone -q "$REPO" "$WORK/graf"
mkdir -p "$WORK/home" "$OUT"
cd "$WORK/graf"
load_before=$(cut -d' ' -f1 /proc/loadavg)
t0=$(date +%s.%N)
HOME="$WORK/home" bash scripts/setup.sh > "$WORK/setup.log" 2>&1
t1=$(date +%s.%N)
HOME="$WORK/home" .venv/bin/graf-train experiment=graf_rfid_s23 hydra.run.dir="$WORK/main_job" > "$WORK/main_job.log" 2>&1
t2=$(date +%s.%N)
cp "$WORK/setup.log" "$WORK/main_job.log" "$OUT/"
cp "$WORK/main_job/results.json" "$OUT/main_job_results.json"
"$REPO/.venv/bin/python" - "$OUT" "$t0" "$t1" "$t2" "$(git rev-parse --short=8 HEAD)" "$load_before" <<'PY'
import datetime, json, os, platform, sys
from pathlib import Path

out, t0, t1, t2, commit, load = Path(sys.argv[1]), *map(float, sys.argv[2:5]), sys.argv[5], float(sys.argv[6])
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), platform.processor())
main = json.loads((out / "main_job_results.json").read_text())
record = {
    "commands": ["bash scripts/setup.sh", ".venv/bin/graf-train experiment=graf_rfid_s23"],
    "setup_s": round(t1 - t0, 1),
    "main_job_s": round(t2 - t1, 1),
    "main_job_training_s": (main.get("timing") or {}).get("fit_s"),
    "fresh": "a fresh clone; HOME an empty folder: no pip cache, no compiled kernel, no LPIPS weights",
    "commit": commit,
    "date": datetime.date.today().isoformat(),
    "machine": {"cpu": cpu, "cores": os.cpu_count()},
    "load_average_before": load,
}
(out / "results.json").write_text(json.dumps(record, indent=2) + "\n")
def mmss(s):
    m, s = divmod(round(s), 60)
    return f"{m} min {s} s" if m else f"{s} s"
(out / "timing.md").write_text(
    f"In a fresh clone with an empty home folder (no pip cache, no compiled kernel, no LPIPS weights), on a "
    f"{record['machine']['cores']}-core CPU ({record['date']}, commit {commit}; its model is in the record), the set-up took "
    f"{mmss(record['setup_s'])} and the main job {mmss(record['main_job_s'])} "
    f"(`sweeps/newcomer_timing/results.json`, made by `bash scripts/time_newcomer.sh`).\n"
)
print(json.dumps(record, indent=2))
PY
