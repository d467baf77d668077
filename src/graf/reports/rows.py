"""graf-report's rows: one per (job, test scene, method) of a study's ``results.json`` files, the settings a
study varies, its method x metric table and its curves (a metric against L, the fine-tuned fraction or the
survey's spacing)."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from graf.app.spec import family
from graf.errors import ConfigError
from graf.metrics.names import REGISTRY
from graf.reports.axes import AXES, AXIS_NAMES
from graf.reports.table import read_run_result

# neighbor reliance (PSNR with true minus with swapped neighbors): a column of the tables, not a figure
RELIANCE = ("test/reliance_db", "reliance dB", "{:.2f}")
# every registered metric's test figure (graf.metrics.names.REGISTRY): (results.json key, label, number format)
TEST_FIGURES = tuple((f"test/{m.name}", m.label, m.fmt) for m in REGISTRY.values())
UNTRAINED = tuple(a.name for a in AXES if a.untrained is not None)  # a baseline's row: not trained
PSNR_TARGETS = (16.0, 18.0, 20.0, 22.0, 25.0)  # dB: "how densely must I measure for X dB?"


def label_hz(label: str) -> float:
    """The frequency of a :func:`band_label` ("915 MHz", "2.412 GHz") in Hz; 0.0 for anything else."""
    parts = label.split()
    if len(parts) != 2 or parts[1] not in ("MHz", "GHz"):
        return 0.0
    try:
        return float(parts[0]) * (1e9 if parts[1] == "GHz" else 1e6)
    except ValueError:
        return 0.0


def ft_fraction(label: str) -> float | None:
    """The fraction a fine-tuning label stands for (``zero-shot``: 0, ``f20``: 0.2); None for any other label."""
    if label == "zero-shot":
        return 0.0
    if label.startswith("f") and label[1:].isdigit():
        return int(label[1:]) / 100.0
    return None


VALIDATION_DIR = "validation"  # a study's validation jobs (graf.reports.distance reads them)
LEFT_OUT = {"base", VALIDATION_DIR}  # folders of a study record that hold no study job


def result_files(runs: Path) -> list[Path]:
    """The ``results.json`` files of ``runs`` (a folder, or one file), those under ``base/`` folders (a study's base
    models) and ``validation/`` folders (a study's validation jobs, :mod:`graf.reports.distance`) left out."""
    if not runs.exists():
        raise ConfigError(f"graf-report: {runs} does not exist")
    if runs.is_file():
        files = [runs]
    else:  # runs may be one run's own folder: its results.json counts
        files = [f for f in sorted(runs.rglob("results.json")) if not LEFT_OUT & set(f.relative_to(runs).parts[:-1])]
    if not files:
        raise ConfigError(f"graf-report: no results.json under {runs} (base/ and validation/ folders are left out)")
    return files


def job_settings(result: dict, job: str) -> dict:
    """The settings of a job that every row of it shares: the job axes of :data:`graf.reports.axes.AXES`, the
    test pool and the survey's spacing."""
    out = {"job": job}
    for a in AXES:
        if a.of_evaluation is None:
            out[a.name] = a.job_value(result)
        if a.name == "finetune":  # where the fine-tuned model's test neighbors came from, beside its fraction
            out["test_pool"] = (result.get("finetune") or {}).get("test_pool", "")
    # the survey's density: median nearest-neighbor distance of the measured training positions (m)
    out["spacing_m"] = (result.get("splits") or {}).get("measured_spacing_m")
    return out


def evaluations(result: dict) -> list[dict]:
    """A job's evaluations: a cross-scene run's list, or the one evaluation of a single-scene run."""
    return result.get("evaluations") or [
        {
            "eval_scene": result.get("eval_scene") or result.get("scene"),
            "within_scene": result.get("within_scene", True),
            "metrics": result.get("metrics", {}),
            "n_test": result.get("n_test"),
            "band_hz": result.get("band_hz"),
            "baselines": result.get("baselines"),
            "splits": result.get("splits"),
        }
    ]


def _figures(tested: dict) -> dict:
    return {k: (tested.get("metrics") or {}).get(k) for k, _, _ in (*TEST_FIGURES, RELIANCE)}


def rows_of(result: dict, job: str) -> list[dict]:
    """One row per (test scene, method) of a job's results.json."""
    ft = result.get("finetune")
    steps = int(result.get("global_step") or 0)
    budget = f"{steps}" if not ft else f"{ft.get('base_steps', '?')}+{ft.get('steps', 0)}"
    common = job_settings(result, job)
    out = []
    for ev in evaluations(result):
        base = {
            **common,
            **{a.name: a.evaluation_value(result, ev) for a in AXES if a.of_evaluation is not None},
            "within_scene": bool(ev.get("within_scene")),
            "n_test": ev.get("n_test"),
        }
        out.append({**base, "method": result.get("method"), "steps": budget, **_figures(ev)})
        for name, b in (ev.get("baselines") or {}).items():
            # a baseline is not trained: it is the same whatever the job trained on
            untrained = {**{a.name: a.untrained for a in AXES if a.untrained is not None}, "within_scene": None}
            out.append({**base, **untrained, "method": name, "steps": "0", **_figures(b)})
    return out


def collect_rows(runs: Path) -> tuple[list[dict], list[Path]]:
    """The rows of every run's results.json under ``runs`` (a baseline tested on the same data in several jobs
    once), and the files read."""
    files = result_files(runs)
    rows, seen = [], set()
    for f in files:
        result = read_run_result(f)
        if result is None:  # a table written into the folder: not a run
            continue
        job = str(f.parent.relative_to(runs.parent if runs.is_file() else runs))
        for r in rows_of(result, job):
            key = json.dumps({k: v for k, v in r.items() if k != "job"}, sort_keys=True, default=str)
            if key not in seen:  # the same baseline on the same data in several jobs: once
                seen.add(key)
                rows.append(r)
    if not rows:
        raise ConfigError(f"graf-report: no run's results.json under {runs} (base/ folders and tables are left out)")
    return rows, files


FIGURES = tuple(k for k, _, _ in (*TEST_FIGURES, RELIANCE))  # a row's figures: averaged over a cell's seeds


def seed_means(rows: list[dict]) -> list[dict]:
    """One row per cell (every setting of a row but its job): each figure the mean over the cell's jobs, which are
    its training seeds (None where no job has it), and ``n_seeds`` their number; the first job names the cell.
    A table or heatmap of a study shows these, never the last seed's row in its place.  Rows that are already
    means (with ``n_seeds``) keep their counts."""
    groups: dict[str, list[dict]] = {}
    for r in rows:
        key = json.dumps({k: v for k, v in r.items() if k not in ("job", "n_seeds", *FIGURES)}, sort_keys=True,
                         default=str)  # fmt: skip
        groups.setdefault(key, []).append(r)
    out = []
    for rs in groups.values():
        n = sum(int(r.get("n_seeds") or 1) for r in rs)
        figures = {
            k: mean(v for r in rs for v in [r.get(k)] * int(r.get("n_seeds") or 1)) for k in FIGURES
        }  # a mean of means weighted by their seeds
        out.append({**rs[0], **figures, "n_seeds": n})
    return out


def seeds_told(counts) -> str:
    """What a table's or figure's cells are, from their rows' ``n_seeds``: "one seed's run a cell", "the mean over
    3 seeds a cell" or "the mean over 1-3 seeds a cell"."""
    n = sorted({int(c) for c in counts}) or [1]
    if n == [1]:
        return "one seed's run a cell"
    return f"the mean over {n[0] if len(n) == 1 else f'{n[0]}-{n[-1]}'} seeds a cell"


def matrices(rows: list[dict]) -> dict:
    """``{method: {metric label: {"rows": trained on, "cols": tested on, "values", "seeds"}}}``: the trained-on x
    test-scene matrix of each method (a baseline's one row: "(no training)"), each cell the mean over the cell's
    seeds (:func:`seed_means`) and ``seeds`` their number (0: no job).  Two cells at one place (an axis the
    matrix does not show varies) stop with a :class:`~graf.errors.ConfigError` rather than one hiding the other."""
    rows = seed_means(rows)
    trained = [r for r in rows if r["steps"] != "0"]
    methods = sorted({r["method"] for r in trained}) + sorted({r["method"] for r in rows if r["steps"] == "0"})
    tr = sorted({r["trained_on"] for r in trained})
    ev = sorted({r["eval_scene"] for r in rows})
    out: dict = {}
    for m in methods:
        baseline = all(r["steps"] == "0" for r in rows if r["method"] == m)
        ylabels = ["(no training)"] if baseline else tr
        values = np.full((len(ylabels), len(ev)), np.nan)
        seeds = np.zeros((len(ylabels), len(ev)), dtype=int)
        cells = {}
        for r in rows:
            if r["method"] != m:
                continue
            i, j = 0 if baseline else tr.index(r["trained_on"]), ev.index(r["eval_scene"])
            if seeds[i, j]:
                raise ConfigError(
                    f"the matrix of {m} has two cells at {ylabels[i]} -> {ev[j]} (a setting the matrix does not "
                    f"show varies: jobs {cells[i, j]} and {r.get('job')})"
                )
            seeds[i, j], cells[i, j] = r["n_seeds"], r.get("job")
        for key, name, _ in TEST_FIGURES:
            v = values.copy()
            for r in rows:
                if r["method"] == m:
                    i, j = 0 if baseline else tr.index(r["trained_on"]), ev.index(r["eval_scene"])
                    v[i, j] = r.get(key) if r.get(key) is not None else np.nan
            out.setdefault(m, {})[name] = {"rows": ylabels, "cols": ev, "values": v.tolist(), "seeds": seeds.tolist()}
    return out


def varying_axes(rows: list[dict]) -> list[str]:
    """The study axes (:data:`graf.reports.axes.AXIS_NAMES`) that take more than one value (baselines' "-" aside)."""
    return [a for a in AXIS_NAMES if len({str(r.get(a)) for r in rows if r["steps"] != "0" or a not in UNTRAINED}) > 1]


def _sort_key(v):
    if isinstance(v, (int, float)):
        return (0, v, "")
    f = ft_fraction(str(v)) if isinstance(v, str) else None
    return (0, f, "") if f is not None else (1, 0, str(v))


def table(rows: list[dict], axes: list[str]) -> tuple[list[str], list[list]]:
    """Method x metric rows, sorted by the study's varying axes (the paper's tables: one block per setting): one
    row per cell, its figures the mean over the cell's seeds (:func:`seed_means`), their number in ``seeds``."""
    header = [*axes, "method", "n_test", "seeds", "steps", *[n for _, n, _ in (*TEST_FIGURES, RELIANCE)]]
    order = sorted(
        seed_means(rows), key=lambda r: ([_sort_key(r.get(a)) for a in axes], r["method"] == "knn", r["method"])
    )
    return header, [
        [r.get(a) for a in axes]
        + [r["method"], r.get("n_test"), r["n_seeds"], r["steps"]]
        + [r.get(k) for k, _, _ in (*TEST_FIGURES, RELIANCE)]
        for r in order
    ]


def mean(values) -> float | None:
    """The mean of the values that are numbers (None and NaN left out); None when there are none."""
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(v)) if v else None


def curve(rows: list[dict], axis: str, same_family: bool) -> dict:
    """``{method: {x: {metric: mean}}}`` over test scenes (same-family pairs only when asked and present)."""
    pick = [r for r in rows if r.get(axis) is not None]
    if same_family:
        fam = [
            r
            for r in pick
            if r["steps"] == "0" or all(family(t) == family(r["eval_scene"]) for t in r["trained_on"].split("+"))
        ]
        pick = fam or pick
    groups = defaultdict(list)
    for r in pick:
        groups[(r["method"], r[axis])].append(r)
    out = defaultdict(dict)
    for (m, x), rs in groups.items():
        # a baseline tested beside several models appears once per (test scene, x): average those
        out[m][x] = {name: mean(r.get(k) for r in rs) for k, name, _ in TEST_FIGURES} | {"n_pairs": len(rs)}
    return {m: dict(sorted(v.items(), key=lambda kv: _sort_key(kv[0]))) for m, v in out.items()}


def spacing_for(points: dict, targets=PSNR_TARGETS) -> dict:
    """``{target dB: the largest survey spacing (m) at which the test PSNR reaches it}`` from a method's
    ``{spacing: {"PSNR": ...}}``, interpolated linearly in log spacing between measured points (None when no
    measured spacing reaches the target)."""
    xs = sorted((float(x), p["PSNR"]) for x, p in points.items() if p.get("PSNR") is not None)
    out = {}
    for t in targets:
        best = None
        for (x0, y0), (x1, y1) in zip(xs, xs[1:]):
            if y0 >= t > y1:  # crosses downward between x0 and x1
                f = (y0 - t) / (y0 - y1)
                best = float(10 ** (math.log10(x0) + f * (math.log10(x1) - math.log10(x0))))
        ok = [x for x, y in xs if y >= t]
        if ok and (best is None or max(ok) > best):
            best = max(ok)
        out[f"{t:g}"] = best
    return out


def short_scenes(trained_on: str) -> str:
    """A training set as a figure title or the ledger names it: one or two scenes by name, more by count ("6
    scenes": six names overlap)."""
    names = trained_on.split("+")
    return trained_on if len(names) <= 2 else f"{len(names)} scenes"
