#!/usr/bin/env bash
# The paper-density studies on a CPU, one job at a time, each into its published record under sweeps/.  Resumable:
# run it again after an interruption and every finished job is skipped (the studies' skip_finished); a job stopped
# mid-way starts over.  From the repository's root, with the project installed (bash scripts/setup.sh):
#
#   bash scripts/paper_studies_cpu.sh [matrix] [nc] [bands] [unseen] [distance] [distance_rfid]   (no argument: the first four)
#
# Each trained model runs its budget from the paper-density learning curves (regime cross_family_val, validated on
# layouts no study tests on: GRaF graf_cpu_scenes_ray_weights 1,000 steps, KNN-DL 3,000; study_budgets in
# conf/study_size/paper.yaml; GRAF_STEPS / GRAF_KNN_DL_STEPS set others).  Missing catalogs are ray-traced on first use.
#   matrix  GRaF, then KNN-DL, on conference_v1 and office_v1, seeds 0-2, each tested on the six layouts, into
#           sweeps/cross_scene_matrix_paper_val (GRAF_MATRIX: another record; GRAF_MATRIX_MODELS="knn_dl": one method).
#           A GRaF job of 3,000 steps took about 35 min on a 2-core Xeon before issue 53's fast training path
#           (26 min of training at 0.5 s/step, 7.5 min of testing 720 spectra); KNN-DL trains with one torch thread.
#   nc      the neighbor-count study, L in {1, 2, 4, 6, 8, 10, 16} (GRAF_NC_L=2,4: a subset), the four same-family
#           pairs, seeds 0-2, into sweeps/neighbor_count_paper_val (GRAF_NC: another record).  Both methods are
#           tested zero-shot from the matrix's own checkpoints: a matrix job trains the same weights as the study's
#           base model of that scene, seed and thread count (the test scenes do not enter training: bit for bit at
#           20 steps), so the bases are not trained twice.  About 75 s a GRaF job here (84 in all).
#   bands   GRaF trained on conference_v1 at each of 915 MHz, 1.8, 2.4 and 3 GHz, tested at each; seed 0
#           (GRAF_BANDS=1.8ghz,2.4ghz: a subset, trained and tested).  With the fast training path (issue 53) a base
#           trains in 11-16 min here (0.22-0.32 s/step, against 0.33-0.54 before), a test takes 1-2 min.
#   unseen  GRaF and KNN-DL trained on the six layouts, tested on bedroom, outdoor and rfid_s23 zero-shot and
#           fine-tuned on 5-100% of each; seed 0.  NeRF2 is left out (hours per scene on a CPU).
#           GRAF_UNSEEN_FINETUNE=none,f20 picks the fractions (the ledger's Tables 1-4 need these two) and
#           GRAF_UNSEEN_BASE_BAND=2.4ghz the base models (2.4ghz: the paper's protocol; scene: also 915 MHz bases for
#           rfid_s23, one more GRaF training).
#   distance the neighbour-distance study (experiment=neighbor_distance): KNN-DL and GRaF's ray_weights and ray_knn
#           trained on conference_v1 and office_v1 with every neighbour within d wavelengths left out, d in
#           GRAF_DISTANCES (default: the experiment's 0,0.5,1,2,4, run as 0.0,4.0,1.0,0.5,2.0: the ends and the middle
#           first), tested on the family's other layouts, seeds 0-2, into sweeps/neighbor_distance_paper
#           (GRAF_DISTANCE: another record); first each GRaF mode's validation job per distance
#           (<record>/validation/), which choose the mode.
#           GRAF_DISTANCE_MODELS: the methods of its study jobs (default: all three; e.g. the chosen mode first).
#   distance_rfid  the same axis within the measured scene rfid_s23 (experiment=neighbor_distance_rfid): KNN-DL and the
#           main job's accurate GRaF (ray_knn, 10,000 steps each), distances GRAF_RFID_DISTANCES (the experiment's:
#           0.0,1.0,0.5), seeds 0-2, into sweeps/neighbor_distance_rfid (GRAF_DISTANCE_RFID: another record); each
#           job a run of its own that resumes from its last.ckpt (then graf-report runs=sweeps/neighbor_distance_rfid).
set -euo pipefail
cd "$(dirname "$0")/.."
TRAIN=${GRAF_TRAIN:-.venv/bin/graf-train}
COMMON=(reliance=false data_root=data)
MATRIX=${GRAF_MATRIX:-sweeps/cross_scene_matrix_paper_val}  # the matrix record (and the checkpoints nc reads)
MATRIX_MODELS=${GRAF_MATRIX_MODELS:-graf_cpu_scenes_ray_weights knn_dl}
NC=${GRAF_NC:-sweeps/neighbor_count_paper_val}
NC_L=${GRAF_NC_L:-1,2,4,6,8,10,16}  # the neighbor counts nc tests (GRAF_NC_L=2,4: the Table 5 rise alone)
budget() {  # a model's study budget: its one home, conf/study_size/paper.yaml (read off its learning curve)
    "${PYTHON:-.venv/bin/python}" -c "from omegaconf import OmegaConf as O; print(O.load('conf/study_size/paper.yaml').study_budgets['$1'])"
}
declare -A STEPS=([graf_cpu_scenes_ray_weights]=${GRAF_STEPS:-$(budget graf_cpu_scenes_ray_weights)}
    [knn_dl]=${GRAF_KNN_DL_STEPS:-$(budget knn_dl)})
declare -A THREADS=([graf_cpu_scenes_ray_weights]=2 [graf_cpu_scenes_ray_knn]=2 [graf_cpu_ray_knn]=2 [knn_dl]=1)
BANDS=${GRAF_BANDS:-915mhz,1.8ghz,2.4ghz,3ghz}  # the bands the bands study trains at and tests at
UNSEEN_FT=${GRAF_UNSEEN_FINETUNE:-none,f05,f10,f20,f50,f100}  # the fine-tuning fractions unseen tests
DISTANCE=${GRAF_DISTANCE:-sweeps/neighbor_distance_paper}  # the neighbour-distance record
DISTANCE_RFID=${GRAF_DISTANCE_RFID:-sweeps/neighbor_distance_rfid}  # the measured scene's neighbour-distance record
RFID_DISTANCES=${GRAF_RFID_DISTANCES:-$("${PYTHON:-.venv/bin/python}" -c "from omegaconf import OmegaConf as O
print(O.load('conf/experiment/neighbor_distance_rfid.yaml').hydra.sweeper.params['neighbors.exclude_within'])")}
ends_first() {  # the study's distances (conf/experiment/neighbor_distance.yaml): the two ends, the middle, then the rest
    "${PYTHON:-.venv/bin/python}" -c "from omegaconf import OmegaConf as O
d = sorted(str(O.load('conf/experiment/neighbor_distance.yaml').hydra.sweeper.params['neighbors.exclude_within']).split(','), key=float)
m = d[len(d) // 2]
print(','.join(dict.fromkeys(d[:1] + d[-1:] + [m] + d[1:-1])))"
}
DISTANCES=${GRAF_DISTANCES:-$(ends_first)}  # its distances (wavelengths), in the order run: the ends, then the middle
# the methods its study jobs train (GRAF_DISTANCE_MODELS="knn_dl graf_cpu_scenes_ray_weights": the mode validation
# chose first, the other one on a later run)
DISTANCE_MODELS=${GRAF_DISTANCE_MODELS:-knn_dl graf_cpu_scenes_ray_weights graf_cpu_scenes_ray_knn}
UNSEEN_BAND=${GRAF_UNSEEN_BASE_BAND:-2.4ghz,scene}  # the base models unseen starts from
STUDIES=("$@")
[ ${#STUDIES[@]} -gt 0 ] || STUDIES=(matrix nc bands unseen)

say() { echo "=== $(date -u +%FT%TZ) $*"; }

for study in "${STUDIES[@]}"; do
    case $study in
    matrix)
        for model in $MATRIX_MODELS; do
            for seed in 0 1 2; do  # seed-major: any prefix of the queue covers both training scenes
                for scene in conference_v1 office_v1; do
                    say "matrix: $model scene=$scene seed=$seed"
                    "$TRAIN" experiment=cross_scene_matrix "model=$model" "scene=$scene" "seed=$seed" \
                        "study_steps=${STEPS[$model]}" "torch_threads=${THREADS[$model]}" "${COMMON[@]}" \
                        hydra.sweep.dir="$MATRIX"
                done
            done
        done
        ;;
    nc)
        for model in $MATRIX_MODELS; do
            run="model=$model,reliance=False,scene=%s,seed=%s,study_steps=${STEPS[$model]},torch_threads=${THREADS[$model]}"
            for scene in conference_v1 office_v1; do
                for seed in 0 1 2; do
                    f="$MATRIX/$(printf "$run" "$scene" "$seed")/checkpoints/last.ckpt"
                    [ -f "$f" ] || { echo "nc: $f is missing: run the matrix first (bash $0 matrix)" >&2; exit 2; }
                done
            done
            ckpt="$MATRIX/$(printf "$run" '${hydra:runtime.choices.scene}' '${seed}')/checkpoints/last.ckpt"
            say "nc: $model, zero-shot from the matrix's checkpoints"
            "$TRAIN" experiment=neighbor_count "model=$model" 'scene=conference_v1,office_v1' \
                finetune.base=null "finetune.init_from=\"$ckpt\"" \
                'hydra.job.config.override_dirname.exclude_keys=[experiment,data_root,study_size,finetune.base,finetune.init_from]' \
                "neighbors.L=$NC_L" "torch_threads=${THREADS[$model]}" "${COMMON[@]}" hydra.sweep.dir="$NC"
        done
        ;;
    bands)
        say "bands: GRaF, seed 0"
        "$TRAIN" experiment=bands seed=0 "band=$BANDS" "eval_band=$BANDS" torch_threads=2 "${COMMON[@]}" hydra.sweep.dir=sweeps/bands_paper
        ;;
    unseen)
        say "unseen layouts: GRaF and KNN-DL, seed 0"
        "$TRAIN" experiment=unseen_layouts 'model=graf_cpu_scenes_ray_weights,knn_dl' seed=0 "finetune=$UNSEEN_FT" \
            "finetune.base.band=$UNSEEN_BAND" torch_threads=2 "${COMMON[@]}" \
            hydra.sweep.dir=sweeps/unseen_layouts_paper
        ;;
    distance)  # validation jobs first (they choose GRaF's mode per distance), then the study, seed-major
        for d in ${DISTANCES//,/ }; do
            for model in graf_cpu_scenes_ray_weights graf_cpu_scenes_ray_knn; do
                say "distance: validation, $model exclude_within=$d"
                "$TRAIN" experiment=neighbor_distance "model=$model" scene=conference_v1 seed=0 \
                    "neighbors.exclude_within=$d" 'eval_scene=[conference_v4,office_v4]' test=false validate=true \
                    "torch_threads=${THREADS[$model]}" "${COMMON[@]}" hydra.sweep.dir="$DISTANCE/validation"
            done
        done
        for seed in 0 1 2; do
            for d in ${DISTANCES//,/ }; do
                for model in $DISTANCE_MODELS; do
                    say "distance: $model exclude_within=$d seed=$seed"
                    "$TRAIN" experiment=neighbor_distance "model=$model" 'scene=conference_v1,office_v1' "seed=$seed" \
                        "neighbors.exclude_within=$d" "torch_threads=${THREADS[$model]}" "${COMMON[@]}" \
                        hydra.sweep.dir="$DISTANCE"
                done
            done
        done
        ;;
    distance_rfid)  # the measured scene within itself, seed-major, the distances in the experiment's order
        for seed in 0 1 2; do
            for d in ${RFID_DISTANCES//,/ }; do
                for model in knn_dl graf_cpu_ray_knn; do
                    # one run per job (10,000 steps: about 40 min for GRaF), resumed from its last.ckpt after a stop
                    dir="$DISTANCE_RFID/model=$model,neighbors.exclude_within=$d,seed=$seed"
                    [ -f "$dir/results.json" ] && { say "done already: $dir"; continue; }
                    ckpt=()
                    [ -f "$dir/checkpoints/last.ckpt" ] && ckpt=("ckpt_path='$dir/checkpoints/last.ckpt'")
                    say "distance_rfid: $model exclude_within=$d seed=$seed ${ckpt[*]}"
                    "$TRAIN" experiment=neighbor_distance_rfid "model=$model" "seed=$seed" "neighbors.exclude_within=$d" \
                        "torch_threads=${THREADS[$model]}" hydra.mode=RUN "hydra.run.dir='$dir'" "${ckpt[@]}"
                done
            done
        done
        ;;
    *)
        echo "unknown study '$study': one of matrix, nc, bands, unseen, distance, distance_rfid" >&2
        exit 2
        ;;
    esac
done
say "done: ${STUDIES[*]}"
