#!/bin/bash
# On the lent GPU: regime cross_family_val, ray / ray_knn / ray_weights / KNN-DL from their 3,000-step checkpoints
# toward 10,000 (one graf-curves process each, at once), SIGTERM (state saved) at DEADLINE s; results tarred to OUT.
set -u
T0=$(date +%s); el() { echo $(( $(date +%s) - T0 )); }
OUT=$1; DEADLINE=${2:-470}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .paper_gpu/wheels/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src GRAF_LPIPS_WEIGHTS=$PWD/.paper_gpu/lpips.ckpt PYTHONUNBUFFERED=1 HYDRA_FULL_ERROR=1
nvidia-smi -L; nproc
[ -f data/sim/office_v4/2.4ghz.h5 ] || python3 .paper_gpu/restore4.py || exit 1
echo "data ready at $(el) s"
MODES="ray ray_knn ray_weights knn_dl"
for m in $MODES; do
  timeout -k 45 -s TERM $((DEADLINE - $(el))) python3 -m graf.cli.studies.curves out=sweeps/learning_curves \
    data_root=data 'only_regimes=[cross_family_val]' "only_methods=[$m]" until=10000 threads=3 \
    "extra_overrides=['trainer=gpu']" > "$OUT/curves_$m.log" 2>&1 &
done
while [ "$(jobs -r | wc -l)" -gt 0 ]; do
  sleep 60
  echo "--- $(el) s"; for m in $MODES; do grep -ao "step [0-9]*\|Epoch [0-9]*: *[0-9]*%[^]]*" "$OUT/curves_$m.log" | tail -1; done
  nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
done
wait
echo "curves ended at $(el) s"
for m in $MODES; do
  tar czf "$OUT/$m.tgz" --exclude='epoch=*' sweeps/learning_curves/cross_family_val/$m/step_10000 2>/dev/null
done
ls -la "$OUT"; echo "all done at $(el) s"
