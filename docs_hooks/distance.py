"""``<!-- gen: distance sweeps/<record> [brief] -->``: where GRaF pays as the neighbours thin out, from the
neighbour-distance study's record (:mod:`graf.reports.distance`): its advice sentence, its figure and (not ``brief``:
the front page) its table; while the record is being made, how many of its jobs have finished and the command that
goes on with it.
"""

from __future__ import annotations

import json
from pathlib import Path

from graf.reports.distance import markdown

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = "bash scripts/paper_studies_cpu.sh distance"


def planned_jobs(distances: int = 3, seeds: int = 3, methods: int = 3, families: int = 2, modes: int = 2) -> int:
    """The jobs of the study's default grid: every method and family at every distance and seed, and one
    validation job per GRaF mode and distance."""
    return methods * families * distances * seeds + modes * distances


def block(arg: str) -> str:
    path, *flags = arg.split()
    folder = ROOT / path
    record = folder / "distance.json"
    done = len(list(folder.rglob("results.json"))) if folder.is_dir() else 0
    if not record.is_file():
        return (
            f"*The neighbour-distance study is under way: {done} of its {planned_jobs()} jobs have finished (the "
            f"distances 0, 1 and 4 wavelengths, 3 seeds). `{SCRIPT}` goes on with it, skipping what has finished; "
            "this section then shows its answer, generated from its record.*"
        )
    data = json.loads(record.read_text())
    seeds = sorted(
        {c["n_seeds"] for fam in data["differences"].values() for row in fam.values() for m in row.values()
         for c in m.values() if isinstance(c, dict) and "n_seeds" in c}
    )  # fmt: skip
    partial = "" if done >= planned_jobs() else f" ({done} of {planned_jobs()} jobs so far; `{SCRIPT}` goes on)"
    return "\n\n".join(
        [
            f"**{data['advice']}**",
            f"![GRaF and KNN-DL against KNN as the nearest neighbour moves away]({path}/vs_distance.png)",
            *([] if "brief" in flags else [markdown(data)]),
            f"*Generated from `{path}/distance.json`: {', '.join(map(str, seeds))} seed(s) per point{partial}.*",
        ]
    )
