"""Two runs of one method on the same test spectra, paired: run A minus run B per metric (95% interval, bootstrap over
spectra: graf.reports.statistics.paired_difference), from their per_spectrum.csv.gz.

python scripts/paired_runs.py RUN_A RUN_B [method]

RUN_A, RUN_B: job folders (each with per_spectrum.csv.gz); method: the method whose rows are paired (default: the
first non-KNN method of RUN_A).  Prints one line per test scene and metric; refuses runs whose test ids differ.
"""

from __future__ import annotations

import csv
import gzip
import sys
from pathlib import Path

from graf.metrics.names import REGISTRY
from graf.reports.statistics import paired_difference


def rows(folder: Path) -> list[dict]:
    path = folder / "per_spectrum.csv.gz"
    if not path.is_file():
        sys.exit(f"{path}: not found (a job folder of graf-train or graf-eval holds one)")
    with gzip.open(path, "rt") as f:
        return list(csv.DictReader(f))


def main() -> None:
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    a_rows, b_rows = rows(Path(sys.argv[1])), rows(Path(sys.argv[2]))
    method = sys.argv[3] if len(sys.argv) == 4 else next(r["method"] for r in a_rows if r["method"] != "knn")
    metrics = [m for m in REGISTRY if m in a_rows[0]]
    for scene in sorted({r["eval_scene"] for r in a_rows if r["method"] == method}):

        def pick(rs, m, scene=scene):
            return {
                int(r["id"]): float(r[m])
                for r in rs
                if r["method"] == method and r["eval_scene"] == scene and r[m] != ""
            }

        if pick(a_rows, "psnr").keys() != pick(b_rows, "psnr").keys():
            sys.exit(f"{scene}: the two runs tested different spectra; a paired difference needs the same ones")
        for m in metrics:
            d = paired_difference([pick(a_rows, m)], [pick(b_rows, m)], m)
            print(
                f"{scene} {method} {m}: A - B = {d['diff']:+.4f} [{d['low']:+.4f}, {d['high']:+.4f}] "
                f"({d['n_spectra']} spectra): {d['verdict']}"
            )


if __name__ == "__main__":
    main()
