"""Copy a finished study's record from multirun/<study> into sweeps/<study>: every job's results.json (and
skipped.json, base_overrides.json, the job log), the multirun's config, and graf-report's tables and figures.
Checkpoints and prediction samples stay behind (they are large; the study's command makes them again).

    python scripts/publish_study.py cross_scene_matrix     (then add the command and wall time in its README.md)
    python scripts/publish_study.py search_neighbor_count (a search: also its optuna.db, trials.csv, best files)
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

KEEP = (
    "results.json",
    "skipped.json",
    "base_overrides.json",
    "multirun.yaml",
    "rows.csv",
    "rows.json",
    "matrix.json",
    "failed.json",
    # searches (hparams_search): the study's storage and its outputs
    "optuna.db",
    "trials.csv",
    "best_params.json",
    "best_overrides.txt",
    "pareto.json",
    "best.json",
)
KEEP_SUFFIX = (".png", ".log")
KEEP_PREFIX = ("report.", "table.")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("study")
    ap.add_argument("--src", default=None, help="default: multirun/<study>")
    ap.add_argument("--dst", default=None, help="default: sweeps/<study>")
    args = ap.parse_args()
    src = Path(args.src or f"multirun/{args.study}")
    dst = Path(args.dst or f"sweeps/{args.study}")
    n = 0
    for f in sorted(src.rglob("*")):
        rel = f.relative_to(src)
        if not f.is_file() or any(p in ("checkpoints", "samples", "csv", ".hydra", "report_logs") for p in rel.parts):
            continue
        if f.name in KEEP or f.suffix in KEEP_SUFFIX or f.name.startswith(KEEP_PREFIX):
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, dst / rel)
            n += 1
    print(f"{n} files from {src} -> {dst}")


if __name__ == "__main__":
    main()
