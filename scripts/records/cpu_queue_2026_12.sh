#!/usr/bin/env bash
# The records still to run on the 2-core CPU (December 2026), one heavy job at a time, in the order their issues
# come; resumable: run it again after a stop and each step goes on where it was (a finished job is skipped, a
# stopped graf-train resumes from its last.ckpt).  Stop it with SIGTERM to its graf-train (the run saves a checkpoint
# and exits 143), never SIGKILL mid-write.  From the repository's root:
#
#   nohup bash scripts/records/cpu_queue_2026_12.sh > queue.log 2>&1 &
#
# Done, and so left out since 2026-12-05: seed 2 of the main job's accurate variant (sweeps/main_job_accurate_seeds/),
# GRaF's half of the cross-scene matrix at the recipe budgets (sweeps/cross_scene_matrix_paper_recipe/) and the
# neighbour-count re-run from it (sweeps/neighbor_count_paper_recipe/): their READMEs have the commands.
#
#   1. the neighbour-distance study (sweeps/neighbor_distance_paper/), and its report: on a CPU whose ray tracer gives
#      that record's catalog (the one KNN's prediction hashes in cross_scene_matrix_paper_val show: an AVX-512 CPU);
#   2. the same axis on the measured scene (sweeps/neighbor_distance_rfid/), and its report;
#   3. RF-GS within each room at its 10,000-step budget (sweeps/rf_gs_paper_10000/), beside the matrix (about 35 min a
#      job on a 2-core CPU: some 3.5 hours);
#   4. the kernel's vector width on a 1,000-step paper-density cell (sweeps/kernel_width/paper_cell/): on a CPU with
#      AVX2 but not AVX-512, where the two widths differ.
set -euo pipefail
cd "$(dirname "$0")/../.."
TRAIN=.venv/bin/graf-train
say() { echo "=== $(date -u +%FT%TZ) $*"; }

bash scripts/paper_studies_cpu.sh distance
.venv/bin/graf-report runs=sweeps/neighbor_distance_paper hydra.run.dir=sweeps/neighbor_distance_paper/report_logs

bash scripts/paper_studies_cpu.sh distance_rfid
.venv/bin/graf-report runs=sweeps/neighbor_distance_rfid hydra.run.dir=sweeps/neighbor_distance_rfid/report_logs

say "rf_gs at its study budget"
"$TRAIN" -m experiment=cross_scene_matrix model=rf_gs eval_scene=same scene=conference_v1,office_v1 seed=0,1,2 \
    torch_threads=1 reliance=false data_root=data hydra.sweep.dir=sweeps/rf_gs_paper_10000
.venv/bin/graf-report runs=sweeps/rf_gs_paper_10000 "compare_with=[sweeps/cross_scene_matrix_paper_recipe]" \
    hydra.run.dir=sweeps/rf_gs_paper_10000/report_logs

if grep -q avx2 /proc/cpuinfo && ! grep -q avx512f /proc/cpuinfo; then  # the two widths differ only here
    for w in 64 32; do  # the kernel's vector width at the paper's density (scripts/records/kernel_width.py)
        dir=sweeps/kernel_width/paper_cell/bytes_$w
        [ -f "$dir/results.json" ] && { say "done already: $dir"; continue; }
        say "kernel width $w bytes: paper cell"
        GRAF_KERNEL_VECTOR_BYTES=$w "$TRAIN" experiment=cross_scene_matrix model=graf_cpu_scenes_ray_weights \
            scene=conference_v1 seed=0 study_steps=1000 'eval_scene=[conference_v2]' torch_threads=2 reliance=false \
            data_root=data hydra.mode=RUN "hydra.run.dir=$dir"
    done
    .venv/bin/python scripts/records/kernel_width.py
fi
say "queue done"
