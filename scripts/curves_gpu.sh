#!/usr/bin/env bash
# Learning-curve points on a lent GPU machine, one graf-curves process per method at once, stopped (SIGTERM: each
# run saves its state, graf-curves records the attempt) at a deadline; each method's newest point comes back as a
# tarball to unpack into sweeps/learning_curves/, where graf-curves on the CPU resumes it.  From the repository's
# root, on the device (carry [".paper_gpu"], made by `SCENES="..." bash scripts/prepare_paper_gpu.sh`, and the
# curves' checkpoints to resume from, which travel with the working tree):
#
#   bash scripts/curves_gpu.sh OUT DEADLINE_S REGIME UNTIL METHOD...
#   e.g. bash scripts/curves_gpu.sh "$OUT" 500 cross_family_val 10000 ray ray_knn ray_weights knn_dl
#
# Each method runs with threads=3 (16 cores there) and trainer=$TRAINER (gpu; a smoke run here:
# TRAINER=cpu PYTHON=.venv/bin/python).
# Record of its use: sweeps/paper_gpu_runs/
set -u
T0=$(date +%s)
el() { echo $(( $(date +%s) - T0 )); }
OUT=$1 DEADLINE=$2 REGIME=$3 UNTIL=$4
shift 4
DIR=.paper_gpu
PY=${PYTHON:-python3}
if ! $PY -c "import hydra, omegaconf" 2>/dev/null; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "$DIR"/wheels/*.whl \
        || exit 1
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="$PWD/src:${PYTHONPATH:-}" GRAF_LPIPS_WEIGHTS="$PWD/$DIR/lpips.ckpt" PYTHONUNBUFFERED=1
nvidia-smi -L
for f in "$DIR"/catalog/*.slim.h5; do  # the spectra rebuilt from the channels (sha256 checked), one process each
    name=$(basename "$f" .slim.h5)
    dst="data/sim/${name%%__*}/${name##*__}.h5"
    [ -f "$dst" ] || { mkdir -p "$(dirname "$dst")" && $PY -m graf.sim.slim restore "$f" "$dst" & }
done
wait
echo "data ready at $(el) s"
for m in "$@"; do
    timeout -k 45 -s TERM $((DEADLINE - $(el))) $PY -m graf.cli.studies.curves out=sweeps/learning_curves \
        data_root=data "only_regimes=[$REGIME]" "only_methods=[$m]" until="$UNTIL" threads=3 \
        "extra_overrides=['trainer=${TRAINER:-gpu}']" > "$OUT/curves_$m.log" 2>&1 &
done
while [ "$(jobs -r | wc -l)" -gt 0 ]; do
    sleep 60
    echo "--- $(el) s: $(nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader)"
done
wait
echo "curves ended at $(el) s"
for m in "$@"; do  # the newest point of each curve (its checkpoint too; ModelCheckpoint's copies left out)
    newest=$(ls -d sweeps/learning_curves/"$REGIME"/"$m"/step_* | awk -F'step_' '{print $NF, $0}' | sort -n \
        | tail -1 | cut -d' ' -f2)
    tar czf "$OUT/$m.tgz" --exclude='epoch=*' "$newest"
done
ls -la "$OUT"
echo "all done at $(el) s"
