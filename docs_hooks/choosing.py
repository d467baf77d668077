"""``<!-- gen: choosing BENCH -->``: the numbers of "Choosing a model", from the records.

Per preset: its training seconds per step and its seconds per spectrum on the CPU (the graf-bench record ``BENCH``,
each preset at its own rays per step, on the embedded real scene and a simulated room), its study budget
(``conf/study_size/paper.yaml``'s, the rule's) and what training to it costs there, what 1,000 steps (graf-train's
default: your own data) cost, the fastest GPU training on record (the learning curves' points trained on one GPU
alone), and its quality on record at the studies' budgets with the paired verdicts against KNN.  Nothing here is
typed: a figure the records lack prints as "-" and says why below the table.
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
# preset, what it is for, its quality's record (a study folder with intervals.json and rows.json) and the method
# name there, and its learning curves' method (for the GPU seconds per step)
PRESETS = (
    ("knn", "no training", "cross_scene_matrix_paper_val", "knn", None),
    ("knn_dl", "learned interpolation", "cross_scene_matrix_paper_val", "knn-dl", "knn_dl"),
    ("graf_cpu_scenes_ray_weights", "GRaF of the studies", "cross_scene_matrix_paper_val", "graf-ray-weights",
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


def _pair(a: float | None, b: float | None) -> str:
    return "-" if a is None and b is None else f"{_seconds(a)} / {_seconds(b)}"


def table(bench: str) -> str:
    """Two tables: what each preset costs (the bench record's real scene, then its simulated room), and its quality
    on record at the studies' budgets."""
    record = json.loads(_read(ROOT / bench / "results.json"))
    by = {(r["preset"], r["scene"]): r for r in record["rows"] if not r.get("error")}
    scenes = list(dict.fromkeys(r["scene"] for r in record["rows"]))
    if len(scenes) != 2:
        raise PluginError(f"docs: {bench}/results.json: the choosing table reads a real scene and a room, not {scenes}")
    real, room = scenes
    own, default = budgets()
    gpu = gpu_step_s()
    cost, good, missing = [], [], []
    for preset, role, study, method, curve in PRESETS:
        budget = own.get(preset, default)
        a, b = by.get((preset, real)) or {}, by.get((preset, room)) or {}
        missing += [f"`{preset}` on {sc}" for sc, r in ((real, a), (room, b)) if not r]
        step_real, step_room = a.get("train_s_per_step"), b.get("train_s_per_step")
        cost.append(
            [
                f"`{preset}`",
                "nothing to train" if preset == "knn" else _pair(step_real, step_room),
                _pair(a.get("infer_s_per_spectrum"), b.get("infer_s_per_spectrum")),
                "none" if preset == "knn" else f"{budget:,}" + ("" if preset in own else " (default)"),
                "-" if step_room is None else _seconds(step_room * budget),
                "-" if step_real is None else _seconds(step_real * OWN_DATA_STEPS),
                "-" if curve not in gpu else f"{gpu[curve][0]:.3g} s ({gpu[curve][1]})",
            ]
        )
        good.append([f"`{preset}`", role, quality(study, method, budget) if study else "-"])
    machine = f"{record.get('device')}, {record.get('threads')} threads"
    head = ["preset", f"s/step ({real} / {room})", "s/spectrum", "study budget (steps)", f"to the budget ({room})",
            f"{OWN_DATA_STEPS:,} steps ({real})", "s/step on one GPU"]  # fmt: skip
    out = published.md(head, cost) + (
        f"\n\n*Generated from `{bench}/results.json` ({machine}; each preset at its own rays per step), "
        "`conf/study_size/paper.yaml` (the budgets) and `sweeps/learning_curves/curves.csv` (the fastest point "
        "trained on one GPU alone)." + (f" Not in the bench record: {', '.join(missing)}." if missing else "") + "*"
    )
    out += "\n\n" + published.md(["preset", "for", "test PSNR at the studies' budget"], good)
    out += (
        "\n\n*Generated from `sweeps/cross_scene_matrix_paper_val/` (zero-shot across layouts, 3 seeds), "
        "`sweeps/rf_gs_paper/` (within each room, 3 seeds) and `sweeps/main_job/`: the mean over the record's cells "
        "and seeds; a verdict against KNN is a paired 95% interval per cell.*"
    )
    return out
