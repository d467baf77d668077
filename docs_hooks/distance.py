"""``<!-- gen: distance sweeps/<record> [brief] [experiment=NAME] -->``: where GRaF pays as the neighbours thin out,
from a neighbour-distance study's record (:mod:`graf.reports.distance`): its advice sentence, its figure and (not
``brief``: the front page) its table; while the record is being made, how many of its jobs have finished and the
command that goes on with it.  ``experiment``: the study's experiment (default ``neighbor_distance``, the rooms;
``neighbor_distance_rfid``: the measured scene), whose grid gives the planned jobs and whose stage of
``scripts/paper_studies_cpu.sh`` goes on with it.
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import OmegaConf

from graf.reports.distance import markdown

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "src" / "graf" / "conf"
EXPERIMENT = "neighbor_distance"


def script(experiment: str = EXPERIMENT) -> str:
    """The command that runs (and goes on with) the study: its stage of scripts/paper_studies_cpu.sh."""
    return f"bash scripts/paper_studies_cpu.sh {experiment.removeprefix('neighbor_')}"


def grid(experiment: str = EXPERIMENT) -> dict[str, list[str]]:
    """The study's default grid: the experiment's sweep, and the seeds of ``study_size=paper`` where it sweeps none."""
    params = dict(OmegaConf.load(CONF / "experiment" / f"{experiment}.yaml").hydra.sweeper.params)
    params.setdefault("seed", OmegaConf.load(CONF / "study_size" / "paper.yaml").hydra.sweeper.params.seed)
    return {k: str(v).split(",") for k, v in params.items()}


def planned_jobs(experiment: str = EXPERIMENT) -> int:
    """The jobs of the default grid: every method and training scene at every distance and seed, and where the study
    compares GRaF modes, one validation job per mode and distance (scripts/paper_studies_cpu.sh)."""
    g = grid(experiment)
    modes = [m for m in g["model"] if m.startswith("graf")]
    validation = len(modes) if len(modes) > 1 else 0  # one mode: fixed before the runs, nothing to choose
    per_distance = len(g["model"]) * len(g.get("scene", [""])) * len(g["seed"]) + validation
    return per_distance * len(g["neighbors.exclude_within"])


def finished_jobs(folder: Path) -> int:
    """The jobs of a neighbour-distance record that have finished so far (each writes its results.json last)."""
    return len(list(folder.rglob("results.json"))) if folder.is_dir() else 0


def seeds(data: dict) -> list[int]:
    """The seed counts of a distance record's points (distance.json): one number when every point has as many."""
    return sorted(
        {c["n_seeds"] for fam in data["differences"].values() for row in fam.values() for m in row.values()
         for c in m.values() if isinstance(c, dict) and "n_seeds" in c}
    )  # fmt: skip


def block(arg: str) -> str:
    path, *flags = arg.split()
    experiment = next((f.split("=", 1)[1] for f in flags if f.startswith("experiment=")), EXPERIMENT)
    folder = ROOT / path
    record = folder / "distance.json"
    done = finished_jobs(folder)
    if not record.is_file():
        g = grid(experiment)
        distances = [f"{d:g}" for d in sorted(float(x) for x in g["neighbors.exclude_within"])]
        return (
            f"*The neighbour-distance study is under way: {done} of its {planned_jobs(experiment)} jobs have "
            f"finished (the distances {', '.join(distances[:-1])} and {distances[-1]} wavelengths, {len(g['seed'])} "
            f"seeds). `{script(experiment)}` goes on with it, skipping what has finished; this section then shows its "
            "answer, generated from its record.*"
        )
    data = json.loads(record.read_text())
    planned = planned_jobs(experiment)
    partial = "" if done >= planned else f" ({done} of {planned} jobs so far; `{script(experiment)}` goes on)"
    return "\n\n".join(
        [
            f"**{data['advice']}**",
            f"![GRaF and KNN-DL against KNN as the nearest neighbour moves away]({path}/vs_distance.png)",
            *([] if "brief" in flags else [markdown(data)]),
            f"*Generated from `{path}/distance.json`: {', '.join(map(str, seeds(data)))} seed(s) per point{partial}.*",
        ]
    )
