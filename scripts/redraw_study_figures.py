"""Redraw a published study's figures with the current plotting code, from its own records only.

    python scripts/redraw_study_figures.py sweeps/cross_scene_matrix sweeps/neighbor_count ...

graf-report would re-read the job folders, but a published folder under ``sweeps/`` keeps the report's rows
(``rows.json``) and the curves' data (``report.json``), not every job's samples.  This redraws from those: the
trained-on x test-scene heatmaps (``matrix_*.png``; each cell the mean over its seeds, report.json's matrices
follow), the metric-against-L, -fraction and -spacing curves (``vs_*.png``) and the band matrix
(``band_matrix.png``), and the method x metric tables (``report.md``, ``.csv``, ``.tex``: a row per cell, the
mean over its seeds).  Rows, intervals and spectra grids are left as they are; a figure whose data the folder does
not hold is skipped and named.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from graf.io import atomic_write_json
from graf.reports.figures import band_figure, curve_figure, matrix_figures
from graf.reports.study import write_tables

CURVES = {  # report.json key -> (x label, file name prefix)
    "vs_L": ("neighbors L at test", "vs_L"),
    "vs_fraction": ("fraction of the new scene's training split (0: zero-shot)", "vs_fraction"),
    "vs_spacing": ("survey spacing: median nearest-neighbor distance (m)", "vs_spacing"),
}


def numeric(data: dict) -> dict:
    """A curve's data as graf-report drew it: JSON made its x keys strings ("2", "0.2"); numbers again."""
    return {m: {float(x): v for x, v in pts.items()} for m, pts in data.items()}


def redraw(folder: Path) -> list[str]:
    rows = json.loads((folder / "rows.json").read_text())["rows"]
    summary = json.loads((folder / "report.json").read_text())
    write_tables(rows, summary["axes"], folder)
    done = ["report.md", "report.csv", "report.tex"]
    if "matrix" in summary:  # its matrices too: each cell the mean over its seeds (report.json's copy follows)
        m = matrix_figures(rows, folder)
        done += m["figures"]
        if summary["matrix"] != m["matrices"]:
            atomic_write_json(folder / "report.json", {**summary, "matrix": m["matrices"]})
            done.append("report.json")
    if "band_matrix" in summary:
        band_figure(rows, folder / "band_matrix.png")
        done.append("band_matrix.png")
    if "vs_L" in summary:
        curve_figure(numeric(summary["vs_L"]), CURVES["vs_L"][0], folder / "vs_L.png",
                     "metric vs L (mean over same-family test pairs)")  # fmt: skip
        done.append("vs_L.png")
    for key in ("vs_fraction", "vs_spacing"):
        for label, data in (summary.get(key) or {}).items():
            if key == "vs_fraction":
                scene, band = label.split(" | trained at ")
                name = f"vs_fraction_{scene}_{band.replace(' ', '')}.png"
                title = f"{scene}: metric vs fine-tuned fraction (models trained at {band})"
            else:
                name, title = f"vs_spacing_{label}.png", f"{label}: metric vs the survey's spacing"
            curve_figure(numeric(data), CURVES[key][0], folder / name, title)
            done.append(name)
    return done


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    for arg in argv:
        folder = Path(arg)
        if not (folder / "rows.json").is_file() or not (folder / "report.json").is_file():
            print(f"{folder}: skipped (no rows.json and report.json: not a graf-report folder)")
            continue
        print(f"{folder}: {', '.join(redraw(folder)) or 'no figure to redraw'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
