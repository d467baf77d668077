#!/usr/bin/env bash
# GRaF's GPU check: on a machine with a CUDA GPU where only Python and torch (and the usual scientific stack)
# are installed, from the repository's root:
#
#   bash scripts/gpu_check.sh [DIR]           (DIR: the folder scripts/prepare_gpu_check.sh made; .gpu_check)
#   bash scripts/gpu_check.sh --tiny [DIR]    (the same steps at toy sizes: runs on a CPU in about a minute)
#
# 1. installs what DIR/wheels holds into DIR/site (no index, no network; skipped where hydra and omegaconf import
#    already or there is no DIR), and points the LPIPS weights and the simulated room at DIR;
# 2. graf-bench at the paper's sizes (GRaF `graf`, NeRF2 `nerf2`) and the studies' GRaF (`graf_cpu_ray_weights`) on the
#    embedded rfid_s23 and the simulated conference_v1, in fp32 and under bf16 autocast: s/spectrum (20 spectra),
#    s/step (20 steps at the paper's 5,120 rays), each after a warm-up, peak GPU memory, trusted per row;
# 3. scripts/gpu_step_profile.py: paper-size GRaF's training step on conference_v1, the grouped path against the
#    static one, fp32 against bf16, at 5,120, 20,480 and 81,920 rays a step: s/step (20 timed), rays/s, and a
#    profiled step's kernel launches and GPU busy share;
# 4. the main job (graf-train experiment=graf_rfid_s23) trained and tested on the GPU;
# and writes everything under sweeps/bench/gpu_<device>/ (GRAF_GPU_CHECK_OUT overrides it): bench_fp32/,
# bench_bf16/, step_profile.json, main_job/, and gpu_check.json + gpu_check.md (each step's seconds, the bench rows, the main
# job's test figures).  The commands run as `python -m graf.cli.<command>` from src/ (no install of graf itself,
# so the machine's own torch stays).  Exit status: non-zero when a step failed (the summary says which).
set -uo pipefail
cd "$(dirname "$0")/.."
TINY=0
if [ "${1:-}" = "--tiny" ]; then TINY=1; shift; fi
DIR=${1:-.gpu_check}
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1 HYDRA_FULL_ERROR=1
STEPS=()
status=0
step() {  # step NAME COMMAND...: run it, record its seconds and exit status
    local name=$1
    shift
    local t0 rc
    t0=$(date +%s%N)
    "$@"
    rc=$?
    STEPS+=("$name $((($(date +%s%N) - t0) / 1000000)) $rc")  # milliseconds
    [ $rc -eq 0 ] || status=$rc
    return 0
}

install() {
    if [ -d "$DIR/wheels" ] && ! "$PY" -c "import hydra, omegaconf" 2>/dev/null; then
        "$PY" -m pip install --quiet --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target "$DIR/site" "$DIR"/wheels/*.whl
    fi
}
step install install
[ -d "$DIR/site" ] && export PYTHONPATH="$PWD/$DIR/site${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
[ -f "$DIR/lpips.ckpt" ] && export GRAF_LPIPS_WEIGHTS="$PWD/$DIR/lpips.ckpt"
DATA=${GRAF_DATA_ROOT:-data}
[ -d "$DIR/data" ] && DATA="$PWD/$DIR/data"

DEVICE=$("$PY" -c "import torch; print(torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'cpu')")
SLUG=$(echo "$DEVICE" | tr 'A-Z' 'a-z' | tr -cs 'a-z0-9' '_' | sed 's/^_//; s/_$//')
OUT=${GRAF_GPU_CHECK_OUT:-sweeps/bench/gpu_$SLUG}
mkdir -p "$OUT"
echo "device: $DEVICE -> $OUT"

BENCH=(data_root="$DATA" "bench.models=[graf,graf_cpu_ray_weights,nerf2]" bench.spectra=20 bench.train_steps=20)
PROFILE=(data_root="$DATA")
TRAIN=(experiment=graf_rfid_s23 trainer=gpu)
if [ $TINY -eq 1 ]; then  # toy sizes, the embedded scene only, on whatever device there is
    BENCH=("bench.scenes=[real]" "bench.models=[graf,nerf2]" quick=true threads=1 "bench.quick_skip=[]"
        bench.rays_per_step=256 models.graf.max_samples=2 "models.graf.encoder_widths=[4,8,8,8]"
        models.graf.encoder_downsample=4 models.nerf2.max_samples=2 models.nerf2.width=16 models.nerf2.depth=2
        "models.nerf2.skips=[]")
    PROFILE=(--tiny)
    TRAIN=(experiment=graf_rfid_s23 trainer=cpu trainer.max_steps=2 model.rays_per_step=64 model.max_samples=4
        data.batch_size=2 "baselines={}" plot_count=1 data.test_subset=2 logger=none)
fi
step bench_fp32 "$PY" -m graf.cli.studies.bench "${BENCH[@]}" precision=32 hydra.run.dir="$OUT/bench_fp32"
step bench_bf16 "$PY" -m graf.cli.studies.bench "${BENCH[@]}" precision=bf16 hydra.run.dir="$OUT/bench_bf16"
step step_profile "$PY" scripts/gpu_step_profile.py "$OUT/step_profile.json" "${PROFILE[@]}"
step main_job "$PY" -m graf.cli.train "${TRAIN[@]}" hydra.run.dir="$OUT/main_job"

"$PY" - "$OUT" "$DEVICE" "$TINY" "${STEPS[@]}" <<'EOF'
import json, sys
from pathlib import Path

out, device, tiny, steps = Path(sys.argv[1]), sys.argv[2], sys.argv[3] == "1", sys.argv[4:]
summary = {"device": device, "tiny": tiny, "steps": {}, "bench": [], "profile": None, "main_job": None}
for s in steps:
    name, ms, rc = s.split()
    summary["steps"][name] = {"seconds": round(int(ms) / 1000, 1), "exit_status": int(rc)}
keys = ("scene", "preset", "method", "samples_per_ray", "infer_s_per_spectrum", "train_s_per_step", "peak_mb_infer",
        "peak_mb_train", "disturbed", "error")
for precision in ("fp32", "bf16"):
    f = out / f"bench_{precision}" / "results.json"
    if f.exists():
        r = json.loads(f.read_text())
        summary["bench"] += [{"precision": precision, **{k: row.get(k) for k in keys},
                              "trusted": not (row.get("disturbed") or row.get("error"))} for row in r["rows"]]
f = out / "step_profile.json"
if f.exists():  # the paper-size training step, path against path: the static path's row at the paper's rays
    rows = json.loads(f.read_text())["rows"]
    summary["step_profile"] = rows
    first = [r for r in rows if r["path"] == "static" and r["precision"] == "fp32" and "error" not in r]
    if first:
        summary["profile"] = {k: first[0].get(k) for k in ("rays_per_step", "s_per_step", "kernel_launches_per_step",
                                                           "gpu_busy_fraction", "operator_calls_per_step",
                                                           "host_reads_per_step", "trusted")}
f = out / "main_job" / "results.json"
if f.exists():
    r = json.loads(f.read_text())
    summary["main_job"] = {k: r.get(k) for k in ("method", "metrics", "baselines", "seconds", "device", "global_step")}
    summary["main_job"]["train_seconds"] = (r.get("timing") or {}).get("fit_s")
(out / "gpu_check.json").write_text(json.dumps(summary, indent=2) + "\n")
lines = [f"# GPU check on {device}" + (" (tiny)" if tiny else ""), "", "| step | seconds | exit |", "|---|---|---|"]
lines += [f"| {k} | {v['seconds']} | {v['exit_status']} |" for k, v in summary["steps"].items()]
lines += ["", "| precision | scene | preset | s/spectrum | s/step | peak MB infer | peak MB train |", "|---|---|---|---|---|---|---|"]
lines += [f"| {b['precision']} | {b['scene']} | {b['preset']} | {b['infer_s_per_spectrum']} | {b['train_s_per_step']} | "
          f"{b['peak_mb_infer']} | {b['peak_mb_train']} |" for b in summary["bench"]]
lines += ["", "| precision | path | rays/step | s/step | rays/s | kernel launches | GPU busy | operators | host reads | "
          "trusted |", "|---|---|---|---|---|---|---|---|---|---|"]
lines += [f"| {r['precision']} | {r['path']} | {r['rays_per_step']} | {r.get('s_per_step')} | {r.get('rays_per_s')} | "
          f"{r.get('kernel_launches_per_step', '-')} | {r.get('gpu_busy_fraction', '-')} | "
          f"{r.get('operator_calls_per_step')} | {r.get('host_reads_per_step')} | {r.get('trusted')} |"
          for r in summary.get("step_profile") or []]
(out / "gpu_check.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
exit $status
