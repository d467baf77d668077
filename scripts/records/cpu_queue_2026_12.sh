#!/usr/bin/env bash
# The records still to run on the 2-core CPU (December 2026), one heavy job at a time, in the order their issues
# come; resumable: run it again after a stop and each step goes on where it was (a finished job is skipped, a
# stopped graf-train resumes from its last.ckpt).  Stop it with SIGTERM to its graf-train (the run saves a checkpoint
# and exits 143), never SIGKILL mid-write.  From the repository's root:
#
#   nohup bash scripts/records/cpu_queue_2026_12.sh > queue.log 2>&1 &
#
#   1. seed 2 of the main job's accurate variant (the headline's three seeds: sweeps/main_job_accurate_seeds/);
#   2. GRaF's half of the cross-scene matrix at the recipe budgets, on this machine's traced catalog
#      (sweeps/cross_scene_matrix_paper_recipe/), and its report;
#   3. the neighbour-count re-run from those checkpoints (sweeps/neighbor_count_paper_recipe/), and its report;
#   4. RF-GS within each room at its 10,000-step budget (sweeps/rf_gs_paper_10000/), beside the matrix;
#   5. the neighbour-distance study (sweeps/neighbor_distance_paper/), and its report;
#   6. the same axis on the measured scene (sweeps/neighbor_distance_rfid/), and its report.
# Between 3 and 4: the kernel's vector width on a 1,000-step paper-density cell (sweeps/kernel_width/paper_cell/).
set -euo pipefail
cd "$(dirname "$0")/../.."
TRAIN=.venv/bin/graf-train
say() { echo "=== $(date -u +%FT%TZ) $*"; }

resume_or_run() {  # a single run into $1 (its results.json: done; its last.ckpt: resume), the rest its overrides
    local dir=$1
    shift
    if [ -f "$dir/results.json" ]; then
        say "done already: $dir"
        return
    fi
    local ckpt=()
    [ -f "$dir/checkpoints/last.ckpt" ] && ckpt=("ckpt_path=$dir/checkpoints/last.ckpt")
    say "run: $dir ${ckpt[*]}"
    "$TRAIN" "$@" "hydra.run.dir=$dir" "${ckpt[@]}"
}

resume_or_run sweeps/main_job_accurate_seeds/seed_2 experiment=graf_rfid_s23_accurate seed=2

export GRAF_MATRIX=sweeps/cross_scene_matrix_paper_recipe
GRAF_MATRIX_MODELS=graf_cpu_scenes_ray_weights bash scripts/paper_studies_cpu.sh matrix
.venv/bin/graf-report "runs=$GRAF_MATRIX" "hydra.run.dir=$GRAF_MATRIX/report_logs"

GRAF_NC=sweeps/neighbor_count_paper_recipe GRAF_MATRIX_MODELS="graf_cpu_scenes_ray_weights knn_dl" GRAF_NC_L=2,4,6,8,10 \
    bash scripts/paper_studies_cpu.sh nc
.venv/bin/graf-report runs=sweeps/neighbor_count_paper_recipe hydra.run.dir=sweeps/neighbor_count_paper_recipe/report_logs

for w in 64 32; do  # the kernel's vector width at the paper's density (sweeps/kernel_width/, scripts/records/kernel_width.py)
    dir=sweeps/kernel_width/paper_cell/bytes_$w
    [ -f "$dir/results.json" ] && { say "done already: $dir"; continue; }
    say "kernel width $w bytes: paper cell"
    GRAF_KERNEL_VECTOR_BYTES=$w "$TRAIN" experiment=cross_scene_matrix model=graf_cpu_scenes_ray_weights \
        scene=conference_v1 seed=0 study_steps=1000 'eval_scene=[conference_v2]' torch_threads=2 reliance=false \
        data_root=data hydra.mode=RUN "hydra.run.dir=$dir"
done
.venv/bin/python scripts/records/kernel_width.py

say "rf_gs at its study budget"
"$TRAIN" -m experiment=cross_scene_matrix model=rf_gs eval_scene=same scene=conference_v1,office_v1 seed=0,1,2 \
    torch_threads=1 reliance=false data_root=data hydra.sweep.dir=sweeps/rf_gs_paper_10000
.venv/bin/graf-report runs=sweeps/rf_gs_paper_10000 "compare_with=[$GRAF_MATRIX]" \
    hydra.run.dir=sweeps/rf_gs_paper_10000/report_logs

bash scripts/paper_studies_cpu.sh distance
.venv/bin/graf-report runs=sweeps/neighbor_distance_paper hydra.run.dir=sweeps/neighbor_distance_paper/report_logs

bash scripts/paper_studies_cpu.sh distance_rfid
.venv/bin/graf-report runs=sweeps/neighbor_distance_rfid hydra.run.dir=sweeps/neighbor_distance_rfid/report_logs
say "queue done"
