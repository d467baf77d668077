#!/usr/bin/env bash
# Prepare the folder scripts/gpu_check.sh installs from (run where the project is set up and PyPI answers):
#
#   bash scripts/prepare_gpu_check.sh [DIR]        (DIR: .gpu_check by default; ignored by git)
#
# DIR/wheels/        the project's dependencies a GPU machine with Python and torch (and the scientific stack:
#                    lightning, numpy, scipy, h5py, matplotlib, ...) usually lacks: hydra-core, omegaconf and
#                    antlr4-python3-runtime at pyproject.toml's versions; all pure Python (any Python >= 3.10).
#                    Another missing package: EXTRA_WHEELS="name==version ..." adds it (pure Python, or a
#                    wheel for the GPU machine's Python: PIP_DOWNLOAD_ARGS="--python-version 3.12 ...").
# DIR/lpips.ckpt     the pretrained LPIPS weights the main job's metrics need (no download there).
# DIR/data/sim/conference_v1/2.4ghz-n64.h5
#                    the bench's simulated room (64 positions; simulated here with Sionna RT if missing), so the
#                    GPU machine needs no ray tracer.
# DIR/MANIFEST.txt   every file with its size and sha256.
# Under 13 MB in all: it fits the 64 MiB a device call may carry (`carry: [".gpu_check"]`).
set -euo pipefail
cd "$(dirname "$0")/.."
DIR=${1:-.gpu_check}
PY=${PYTHON:-.venv/bin/python}
rm -rf "$DIR.tmp" && mkdir -p "$DIR.tmp/wheels" "$DIR.tmp/data/sim/conference_v1"
# shellcheck disable=SC2086
"$PY" -m pip download --quiet --no-deps --only-binary=:all: ${PIP_DOWNLOAD_ARGS:-} -d "$DIR.tmp/wheels" \
    hydra-core==1.3.8 omegaconf==2.3.1 ${EXTRA_WHEELS:-}
"$PY" -m pip wheel --quiet --no-deps -w "$DIR.tmp/wheels" antlr4-python3-runtime==4.9.3  # an sdist on PyPI
"$PY" -m graf.metrics.lpips_weights >/dev/null  # fetched into the cache if missing (sha256-checked)
cp "$("$PY" -c 'from graf.metrics.lpips_weights import find_weights; print(find_weights())')" "$DIR.tmp/lpips.ckpt"
ROOM=data/sim/conference_v1/2.4ghz-n64.h5
if [ ! -f "$ROOM" ]; then
    "$PY" -m graf.cli.sim.simulate scene=conference_v1 band=2.4ghz sim.num_tx=64 data_root=data \
        hydra.run.dir="$DIR.tmp/simulate"
fi
cp "$ROOM" "$DIR.tmp/$ROOM"
(cd "$DIR.tmp" && find . -type f ! -name MANIFEST.txt | sort | xargs sha256sum > MANIFEST.txt)
rm -rf "$DIR" && mv "$DIR.tmp" "$DIR"
du -sh "$DIR"
echo "prepared $DIR: carry it to the GPU machine beside the repository, then: bash scripts/gpu_check.sh $DIR"
