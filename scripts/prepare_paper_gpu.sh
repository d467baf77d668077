#!/usr/bin/env bash
# Prepare the folder scripts/paper_studies_gpu.py reads on a lent GPU machine (run here, where the project is set up):
#
#   bash scripts/prepare_paper_gpu.sh [DIR]          (DIR: .paper_gpu by default; ignored by git)
#
# DIR/wheels/, DIR/lpips.ckpt   as scripts/prepare_gpu_check.sh makes them (what such a machine lacks)
# DIR/catalog/<scene>__<band>.slim.h5
#                               the six conference/office layouts' paper-density catalog files (5,400 positions each)
#                               without their spectra (graf.sim.slim: about 1 MB each instead of 67); traced here with
#                               Sionna RT first if missing, so the GPU machine needs no ray tracer
# About 15 MB in all: it fits the 64 MiB a device call may carry (`carry: [".paper_gpu"]`).
set -euo pipefail
cd "$(dirname "$0")/.."
DIR=${1:-.paper_gpu}
PY=${PYTHON:-.venv/bin/python}
SCENES=${SCENES:-"conference_v1 conference_v2 conference_v3 office_v1 office_v2 office_v3"}
bash scripts/prepare_gpu_check.sh "$DIR.base" >/dev/null
rm -rf "$DIR.tmp" && mkdir -p "$DIR.tmp/catalog"
cp -r "$DIR.base/wheels" "$DIR.base/lpips.ckpt" "$DIR.tmp/"
rm -rf "$DIR.base"
for s in $SCENES; do
    f=data/sim/$s/2.4ghz.h5
    [ -f "$f" ] || "$PY" -m graf.cli.sim.simulate scene="$s" band=2.4ghz data_root=data hydra.run.dir="$DIR.tmp/simulate_$s"
    "$PY" -m graf.sim.slim slim "$f" "$DIR.tmp/catalog/${s}__2.4ghz.slim.h5"
done
(cd "$DIR.tmp" && find . -type f ! -name MANIFEST.txt | sort | xargs sha256sum > MANIFEST.txt)
rm -rf "$DIR" && mv "$DIR.tmp" "$DIR"
du -sh "$DIR"
