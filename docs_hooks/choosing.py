"""``<!-- gen: choosing sweeps -->``: the numbers of "Choosing a model", from the records of the runs themselves.

Per preset: its training seconds per step and its seconds per spectrum at test, the median over the jobs of the record
that trained it as the studies (or the main job) do, with the torch threads they ran on; its study budget
(``conf/study_size/paper.yaml``'s, the rule's) and what training to it costs; the fastest GPU point on record (the
learning curves' points trained on one GPU alone); and its quality on record at the studies' budgets with the paired
verdicts against KNN.  A row times "your own data": the own-data how-to's GRaF at graf-train's default 1,000 steps,
at the main job's seconds per step.  A figure the records lack prints as "-".
"""

from __future__ import annotations

import csv
import json
import statistics
from pathlib import Path

from mkdocs.exceptions import PluginError
from omegaconf import OmegaConf

from graf.reports import published

ROOT = Path(__file__).resolve().parents[1]
STUDY_SIZE = ROOT / "src" / "graf" / "conf" / "study_size" / "paper.yaml"
CURVES = ROOT / "sweeps" / "learning_curves" / "curves.csv"
OWN_DATA_STEPS = 1000  # conf/trainer/default.yaml's max_steps (checked in tests/test_docs_layout.py)
OWN_DATA_PRESET = "graf_cpu_ray_weights"  # the own-data how-to's GRaF
RECIPE = "cross_scene_matrix_paper_recipe"  # the matrix at the budgets validated on its recipe (GRaF 1,000, KNN-DL 300)
# preset, what it is for, its quality's record (a study folder with intervals.json and rows.json) and the method
# name there, and its learning curves' method (for the GPU seconds per step)
PRESETS = (
    ("knn", "no training", RECIPE, "knn", None),
    ("knn_dl", "learned interpolation", RECIPE, "knn-dl", "knn_dl"),
    ("graf_cpu_scenes_ray_weights", "GRaF of the studies", RECIPE, "graf-ray-weights",
     "ray_weights"),
    ("graf_cpu_ray_weights", "GRaF of the main job", "main_job", "graf-ray-weights", "ray_weights"),
    ("rf_gs", "per-scene, no rays", "rf_gs_paper", "rf-gs", "rf_gs"),
    ("nerf2_cpu", "per-scene field", None, None, "nerf2"),
)  # fmt: skip


def _read(path: Path) -> str:
    if not path.is_file():
        raise PluginError(f"docs: {path.relative_to(ROOT)} is missing: the page asks for the choosing table of it")
    return path.read_text()


def _seconds(s: float | None) -> str:
    if s is None:
        return "-"
    if s < 1:
        return f"{s:.3g} s"
    if s < 120:
        return f"{s:.0f} s"
    return f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.1f} h"


# where each preset's seconds are read: a study's jobs or one run ("job", folder, method), or a curve's CPU points
# ("curve", regime, method)
TIMING = {
    "knn_dl": ("job", RECIPE, "knn-dl"),
    "graf_cpu_scenes_ray_weights": ("job", RECIPE, "graf-ray-weights"),
    "graf_cpu_ray_weights": ("job", "main_job", "graf-ray-weights"),
    "rf_gs": ("job", "rf_gs_paper", "rf-gs"),
    "nerf2_cpu": ("curve", "rfid_sparse", "nerf2"),
}


def budgets() -> tuple[dict, int]:
    size = OmegaConf.load(STUDY_SIZE)
    return dict(size.study_budgets), int(size.study_budget_default)


def gpu_step_s() -> dict[str, tuple[float, str]]:
    """Per curve method, the fastest seconds per step of a point trained on one GPU alone (device a GPU's name)."""
    out: dict[str, tuple[float, str]] = {}
    for r in csv.DictReader(_read(CURVES).splitlines()):
        dev, s = r.get("device") or "", r.get("s_per_step") or ""
        if not s or dev in ("", "cpu", "n/a") or "+" in dev:
            continue
        if r["method"] not in out or float(s) < out[r["method"]][0]:
            out[r["method"]] = (float(s), dev)
    return out


def main_job_quality(method: str, budget: int) -> str:
    """The main job's record: its test PSNR and KNN's on the same spectra (one seed: no interval)."""
    r = json.loads(_read(ROOT / "sweeps" / "main_job" / "results.json"))
    if r["method"] != method:
        raise PluginError(f"docs: sweeps/main_job/results.json is a {r['method']} run, not {method}")
    ran = f"; trained {r['global_step']:,} steps" if r["global_step"] != budget else ""
    return (
        f"{r['metrics']['test/psnr']:.2f} dB against KNN's {r['baselines']['knn']['metrics']['test/psnr']:.2f} on "
        f"{r['n_test']} spectra of {r['scene']}, one seed{ran}"
    )


def quality(study: str, method: str, budget: int) -> str:
    """Mean test PSNR over the record's cells, and how the paired intervals against KNN come out in PSNR."""
    if study == "main_job":
        return main_job_quality(method, budget)
    rows = json.loads(_read(ROOT / "sweeps" / study / "rows.json"))["rows"]
    mine = [r for r in rows if r["method"] == method and r.get("test/psnr") not in (None, "")]
    if not mine:
        return "-"
    cells = {(r["trained_on"], r["eval_scene"]) for r in mine}
    said = f"{statistics.mean(float(r['test/psnr']) for r in mine):.2f} dB, {len(cells)} cells"
    if method == "knn":
        return said
    steps = sorted({int(r["steps"]) for r in mine})
    if steps != [budget]:
        said += f" (trained {', '.join(f'{s:,}' for s in steps)} steps, not the budget)"
    iv = json.loads(_read(ROOT / "sweeps" / study / "intervals.json"))["rows"]
    verdicts = [
        r["vs_knn"]["verdict"] for r in iv if r["method"] == method and r["metric"] == "psnr" and r.get("vs_knn")
    ]
    ahead, behind = sum(v == "ahead" for v in verdicts), sum(v == "behind" for v in verdicts)
    return f"{said}; against KNN {ahead} ahead, {len(verdicts) - ahead - behind} level, {behind} behind"


def budget_label(preset: str, budget: int, own: dict) -> str:
    if preset == "knn":
        return "none"
    return f"{budget:,}" if preset in own else f"{budget:,} (study_budget_default)"


def job_timing(folder: str, method: str) -> tuple[float | None, float | None, int | None, int]:
    """(median training s/step, median test s/spectrum, torch threads, jobs) over the jobs of ``method`` under
    ``sweeps/<folder>`` (a study) or of ``sweeps/<folder>/results.json`` (one run)."""
    base = ROOT / "sweeps" / folder
    files = [base / "results.json"] if (base / "results.json").is_file() else sorted(base.glob("*/results.json"))
    jobs = [json.loads(f.read_text()) for f in files]
    jobs = [j for j in jobs if j.get("method") == method and j.get("timing")]
    if not jobs:
        raise PluginError(f"docs: sweeps/{folder} holds no job of {method} with its timing")
    step = [j["timing"]["fit_s_per_step"] for j in jobs if j["timing"].get("fit_s_per_step")]
    spec = [j["timing"]["test_s_per_spectrum"] for j in jobs if j["timing"].get("test_s_per_spectrum")]
    threads = {(j.get("config") or {}).get("torch_threads") for j in jobs}
    return (
        statistics.median(step) if step else None,
        statistics.median(spec) if spec else None,
        threads.pop() if len(threads) == 1 else None,
        len(jobs),
    )


def curve_timing(regime: str, method: str) -> tuple[float | None, int]:
    """(median s/step of the curve's points trained on the CPU, points) of ``method`` in ``regime``."""
    rows = [r for r in csv.DictReader(_read(CURVES).splitlines()) if r["regime"] == regime and r["method"] == method]
    step = [float(r["s_per_step"]) for r in rows if r.get("device") == "cpu" and r.get("s_per_step")]
    return (statistics.median(step) if step else None), len(step)


def table(arg: str) -> str:
    """Two tables: what each preset costs, from the runs that trained it, and its quality on record at the studies'
    budgets."""
    if arg != "sweeps":
        raise PluginError(f"docs: <!-- gen: choosing {arg} -->: the table is made from sweeps")
    own, default = budgets()
    gpu = gpu_step_s()
    cost, good = [], []
    for preset, role, study, method, curve in PRESETS:
        budget = own.get(preset, default)
        source = TIMING.get(preset)
        step = spec = threads = None
        where = "-"
        if source and source[0] == "curve":
            step, n = curve_timing(source[1], source[2])
            where = f"`sweeps/learning_curves/` ({source[1]}, {n} points)"
        elif source:
            step, spec, threads, n = job_timing(source[1], source[2])
            on = "torch's default threads" if threads is None else f"{threads} thread{'s' if threads != 1 else ''}"
            jobs = f"{n} job{'s' if n > 1 else ''}"
            where = f"`sweeps/{source[1]}/` ({jobs}, {on})"
        cost.append(
            [
                f"`{preset}`",
                "nothing to train" if preset == "knn" else _seconds(step),
                _seconds(spec),
                budget_label(preset, budget, own),
                "-" if step is None or preset == "knn" else _seconds(step * budget),
                "-" if curve not in gpu else f"{gpu[curve][0]:.3g} s ({gpu[curve][1]})",
                where,
            ]
        )
        good.append([f"`{preset}`", role, quality(study, method, budget) if study else "-"])
    step, spec, threads, _ = job_timing(*TIMING[OWN_DATA_PRESET][1:])
    cost.append(
        [
            f"your own data: `{OWN_DATA_PRESET}`",
            _seconds(step),
            _seconds(spec),
            f"{OWN_DATA_STEPS:,} (graf-train's default)",
            _seconds(step * OWN_DATA_STEPS),
            "-",
            f"`sweeps/{TIMING[OWN_DATA_PRESET][1]}/` (the main job)",
        ]
    )
    head = ["preset", "training s/step", "s/spectrum at test", "study budget (steps)", "training to the budget",
            "s/step on one GPU", "timed in"]  # fmt: skip
    out = published.md(head, cost) + (
        "\n\n*Generated from the runs' `results.json` (`timing`: the median over a record's jobs), "
        "`conf/study_size/paper.yaml` (the budgets) and `sweeps/learning_curves/curves.csv` (NeRF2's CPU points, and "
        "the fastest point trained on one GPU alone). The CPU figures are the 2-core CPUs each record's README names: "
        "a study trains on a simulated room, the main job and NeRF2's curve on the embedded real scene.*"
    )
    out += "\n\n" + published.md(["preset", "for", "test PSNR at the studies' budget"], good)
    out += (
        f"\n\n*Generated from `sweeps/{RECIPE}/` (KNN, KNN-DL and GRaF; zero-shot across layouts, 3 seeds), "
        "`sweeps/rf_gs_paper/` (within each room, 3 seeds) and `sweeps/main_job/`: the mean over the record's cells "
        "and seeds; a verdict against KNN is a paired 95% interval per cell.*"
    )
    return out
