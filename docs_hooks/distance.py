"""``<!-- gen: distance sweeps/<record> [brief] -->``: where GRaF pays as the neighbours thin out, from the
neighbour-distance study's record (:mod:`graf.reports.distance`): its advice sentence, its figure and (not ``brief``:
the front page) its table; while the record is being made, how many of its jobs have finished and the command that
goes on with it.
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import OmegaConf

from graf.reports.distance import markdown

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "src" / "graf" / "conf"
SCRIPT = "bash scripts/paper_studies_cpu.sh distance"


def grid() -> dict[str, list[str]]:
    """The study's default grid: the sweep of ``experiment=neighbor_distance`` and the seeds of ``study_size=paper``."""
    params = dict(OmegaConf.load(CONF / "experiment" / "neighbor_distance.yaml").hydra.sweeper.params)
    params["seed"] = OmegaConf.load(CONF / "study_size" / "paper.yaml").hydra.sweeper.params.seed
    return {k: str(v).split(",") for k, v in params.items()}


def planned_jobs() -> int:
    """The jobs of the default grid: every method and family at every distance and seed, and one validation job per
    GRaF mode and distance (scripts/paper_studies_cpu.sh distance)."""
    g = grid()
    modes = [m for m in g["model"] if m.startswith("graf")]
    per_distance = len(g["model"]) * len(g["scene"]) * len(g["seed"]) + len(modes)
    return per_distance * len(g["neighbors.exclude_within"])


def block(arg: str) -> str:
    path, *flags = arg.split()
    folder = ROOT / path
    record = folder / "distance.json"
    done = len(list(folder.rglob("results.json"))) if folder.is_dir() else 0
    if not record.is_file():
        g = grid()
        distances = [f"{float(d):g}" for d in g["neighbors.exclude_within"]]
        return (
            f"*The neighbour-distance study is under way: {done} of its {planned_jobs()} jobs have finished (the "
            f"distances {', '.join(distances[:-1])} and {distances[-1]} wavelengths, {len(g['seed'])} seeds). "
            f"`{SCRIPT}` goes on with it, skipping what has finished; this section then shows its answer, generated "
            "from its record.*"
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
