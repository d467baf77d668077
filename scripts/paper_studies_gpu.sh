#!/usr/bin/env bash
# The paper-density studies on a lent GPU machine where only Python and torch (and the usual scientific stack) are
# installed: installs DIR/wheels into /tmp/site (no network), then runs scripts/paper_studies_gpu.py (see its
# docstring) with the LPIPS weights and the catalog from DIR.  From the repository's root:
#
#   bash scripts/paper_studies_gpu.sh OUT [DIR] [options of paper_studies_gpu.py]     (DIR: .paper_gpu)
#
# Prepared here by `bash scripts/prepare_paper_gpu.sh`; on the device: carry [".paper_gpu"], OUT="$OUT".
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=$1
DIR=${2:-.paper_gpu}
shift 2 || shift $#
PY=${PYTHON:-python3}
if ! "$PY" -c "import hydra, omegaconf" 2>/dev/null; then
    "$PY" -m pip install --quiet --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        "$DIR"/wheels/*.whl || exit 1
    export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" GRAF_LPIPS_WEIGHTS="$PWD/$DIR/lpips.ckpt"
export PYTHONUNBUFFERED=1 HYDRA_FULL_ERROR=1
exec "$PY" scripts/paper_studies_gpu.py --pack "$DIR" --out "$OUT" "$@"
