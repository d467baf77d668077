#!/usr/bin/env bash
# Before/after figures of the GRaF geometry changes (issue 9 point 5): the same command on each commit.
# usage: scripts/records/graf_geometry_rfid_s23_run.sh NAME=COMMIT ...   (resumable: a finished run is skipped)
set -u
cd /work/main
for pair in "$@"; do
  name=${pair%%=*}; commit=${pair#*=}
  out=/tmp/measure/$name
  [ -f $out/results.json ] && { echo "skip $name"; continue; }
  rm -rf /tmp/wt_$name; git worktree add -f --detach /tmp/wt_$name $commit >/dev/null 2>&1
  start=$(date +%s)
  OMP_NUM_THREADS=2 PYTHONPATH=/tmp/wt_$name/src .venv/bin/graf-train experiment=graf_rfid_s23_sparse \
    trainer.max_steps=1500 model.decay_steps=1500 \
    trainer.enable_progress_bar=false logger=none plot_count=0 hydra.run.dir=$out > /tmp/measure/$name.log 2>&1
  echo "$name $commit rc=$? $(( $(date +%s) - start )) s" >> /tmp/measure/done.txt
  git worktree remove --force /tmp/wt_$name
done
