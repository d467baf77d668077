"""graf-report: the tables and figures of a study folder.

    graf-report runs=multirun/cross_scene_matrix [out=sweeps/cross_scene_matrix]

Reads every ``results.json`` under ``runs`` (the models a study trains first, under ``base/`` folders, are
left out: their figures are the study's jobs' starting points, not its results) and writes into ``out``
(default: ``runs``):

- ``rows.csv`` / ``rows.json``: one row per (job, test scene, method), baselines tested inside a job
  included (once where several jobs tested the same baseline on the same data);
- ``report.md``, ``report.csv``, ``report.tex``: method x metric (MSE, LPIPS, PSNR, SSIM; the paper's
  tables) with the number of test spectra and the training budget (steps), one block per setting that
  varies in the study (trained on, train band, fine-tuning, L, test scene, test band);
- figures (PNG), each when its axes vary in the study: ``matrix_<metric>.png`` (trained-on x test-scene
  heatmap per method), ``vs_L.png`` (metric vs neighbor count, averaged over the same-family pairs:
  conference_v1 -> v2/v3 and office_v1 -> v2/v3), ``vs_fraction.png`` (metric vs fine-tuned fraction per
  test scene; zero-shot at 0), ``band_matrix.png`` (train band x test band per method), and
  ``spectra_<scene>.png``: the same test positions, true and predicted by every method (from the jobs'
  ``samples/``, ``save_samples=N``);
- ``README.md``: the tables and the paired intervals between the markers of :mod:`graf.reports.readme`, the text
  around them kept (``readme_only=true``: only this, from ``out``'s own ``report.json``, ``rows.json`` and
  ``intervals.json``, no job read again: how a published record's README is refreshed).

A study's multirun calls it when it ends (:class:`StudyReport`, a Hydra callback); it is also this command.
"""

from __future__ import annotations

import logging
import math
import subprocess
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from graf.app.config import task_wrapper
from graf.app.launch import command
from graf.io import atomic_write_bytes, atomic_write_json
from graf.reports.axes import AXIS_NAMES
from graf.reports.distance import write_distance
from graf.reports.figures import band_figure, curve_figure, matrix_figures, spectra_grids
from graf.reports.intervals import write_intervals
from graf.reports.readme import refresh
from graf.reports.rows import (
    PSNR_TARGETS,
    RELIANCE,
    TEST_FIGURES,
    collect_rows,
    curve,
    ft_fraction,
    spacing_for,
    table,
    varying_axes,
)
from graf.reports.table import to_csv
from graf.reports.table import to_markdown as table_markdown

log = logging.getLogger("graf")


def _fmt(v, col: str) -> str:
    spec = {n: s for _, n, s in (*TEST_FIGURES, RELIANCE)}.get(col)
    if v is None:
        return ""
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    return spec.format(v) if spec and isinstance(v, (int, float)) else str(v)


def to_markdown(header, body) -> str:
    return table_markdown(header, body, _fmt)


def to_latex(header, body) -> str:
    esc = lambda s: str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")  # noqa: E731
    lines = [
        r"\begin{tabular}{" + "l" * (len(header) - len(TEST_FIGURES) - 1) + "r" * (len(TEST_FIGURES) + 1) + "}",
        r"\toprule",
        " & ".join(esc(h) for h in header) + r" \\",
        r"\midrule",
    ]
    lines += [" & ".join(esc(_fmt(v, c)) for v, c in zip(row, header)) + r" \\" for row in body]
    return "\n".join(lines + [r"\bottomrule", r"\end{tabular}"]) + "\n"


def write_tables(rows: list[dict], axes: list[str], out: Path) -> None:
    """report.md, report.csv and report.tex (method x metric), and rows.csv (every row)."""
    header, body = table(rows, axes)
    atomic_write_bytes(out / "report.md", to_markdown(header, body).encode())
    atomic_write_bytes(out / "report.csv", to_csv(header, body).encode())
    atomic_write_bytes(out / "report.tex", to_latex(header, body).encode())
    cols = [
        "job",
        *AXIS_NAMES,
        "within_scene",
        "test_pool",
        "method",
        "n_test",
        "steps",
        *[k for k, _, _ in TEST_FIGURES],
    ]
    atomic_write_bytes(out / "rows.csv", to_csv(cols, [[r.get(c) for c in cols] for r in rows]).encode())


def _fraction_curves(rows: list[dict], out: Path, summary: dict) -> None:
    """A metric against the fine-tuned fraction, per test scene and training band (0: zero-shot)."""
    summary["vs_fraction"] = {}
    for key in sorted({(r["eval_scene"], r["train_band"]) for r in rows if r["steps"] != "0"}):
        sub = [r for r in rows if r["eval_scene"] == key[0] and r["train_band"] in (key[1], "-")]
        data = curve([{**r, "fraction": ft_fraction(r["finetune"])} for r in sub], "fraction", False)
        name = f"vs_fraction_{key[0]}_{key[1].replace(' ', '')}.png"
        curve_figure(
            data,
            "fraction of the new scene's training split (0: zero-shot)",
            out / name,
            f"{key[0]}: metric vs fine-tuned fraction (models trained at {key[1]})",
        )
        summary["vs_fraction"][f"{key[0]} | trained at {key[1]}"] = data
        summary["figures"].append(name)


def _spacing_curves(rows: list[dict], out: Path, summary: dict) -> None:
    """A density study (methods trained on thinned surveys of the scene they are tested on): a metric against the
    survey's spacing, and the largest spacing that reaches each PSNR target, per test scene."""
    summary["vs_spacing"], summary["spacing_for_psnr"] = {}, {}
    for scene in sorted({r["eval_scene"] for r in rows}):
        sub = [{**r, "spacing": round(float(r["spacing_m"]), 5)} for r in rows if r["eval_scene"] == scene]
        data = curve([r for r in sub if r["spacing_m"]], "spacing", False)
        name = f"vs_spacing_{scene}.png"
        curve_figure(data, "survey spacing: median nearest-neighbor distance (m)", out / name,
                     f"{scene}: metric vs the survey's spacing")  # fmt: skip
        summary["vs_spacing"][scene] = data
        summary["spacing_for_psnr"][scene] = {m: spacing_for(pts, PSNR_TARGETS) for m, pts in data.items()}
        summary["figures"].append(name)


def make_report(runs: Path, out: Path, reference: dict, compare_with: list[Path] = ()) -> dict:
    """The tables and figures of the study under ``runs``, written into ``out``; the summary (report.json).
    ``reference``: the setting of each varied axis whose jobs the spectra grids show; ``compare_with``: other
    study records whose trained methods the paired intervals compare with too (conf/report.yaml)."""
    rows, files = collect_rows(runs)
    out.mkdir(parents=True, exist_ok=True)
    axes = varying_axes(rows)
    write_tables(rows, axes, out)
    summary = {"runs": str(runs), "n_results": len(files), "n_rows": len(rows), "axes": axes, "figures": []}
    if "L" in axes:
        data = curve(rows, "L", same_family=True)
        curve_figure(data, "neighbors L at test", out / "vs_L.png", "metric vs L (mean over same-family test pairs)")
        summary["vs_L"] = data
        summary["figures"].append("vs_L.png")
    if "finetune" in axes:
        _fraction_curves(rows, out, summary)
    if (
        "finetune" in axes
        and any(r.get("spacing_m") for r in rows)
        and not any(r["within_scene"] is False for r in rows)
    ):
        _spacing_curves(rows, out, summary)
    if "eval_band" in axes and "train_band" in axes and "eval_scene" not in axes and "finetune" not in axes:
        # a band x band matrix of one layout (bands); not when the band changes with the test scene
        summary["band_matrix"] = band_figure(rows, out / "band_matrix.png")
        summary["figures"].append("band_matrix.png")
    elif "eval_scene" in axes and "trained_on" in axes and not {"L", "finetune", "exclude_within"} & set(axes):
        m = matrix_figures(rows, out)
        summary["matrix"] = m["matrices"]
        summary["figures"] += m["figures"]
    if "exclude_within" in axes and (distance := write_distance(runs, out)) is not None:
        summary["figures"].append("vs_distance.png")
        summary["advice"] = distance["advice"]
    summary["figures"] += spectra_grids(rows, runs, out, axes, reference)
    intervals = write_intervals(runs, out, compare_with)
    if intervals is not None:
        summary["intervals"] = "intervals.md"
    atomic_write_json(out / "rows.json", {"rows": rows})
    atomic_write_json(out / "report.json", summary)
    refresh(out)
    return summary


@task_wrapper
def report(cfg: DictConfig) -> dict:
    """graf-report: write and print the tables of the study under ``cfg.runs``."""
    runs = Path(str(cfg.runs))
    out = Path(str(cfg.out)) if cfg.get("out") else runs
    if cfg.get("readme_only"):
        print(f"{refresh(out)}: its generated block made from {out}'s report.json, rows.json and intervals.json")
        return {"readme": str(out / "README.md")}
    others = [Path(str(p)) for p in cfg.get("compare_with") or []]
    summary = make_report(runs, out, OmegaConf.to_container(cfg.reference), others)
    print((out / "report.md").read_text())
    print(
        f"{summary['n_results']} results, {summary['n_rows']} rows; varying: {', '.join(summary['axes']) or 'none'}; "
        f"figures: {', '.join(summary['figures']) or 'none'} -> {out}"
    )
    return summary


class StudyReport(Callback):
    """Hydra callback: at the end of a study's multirun, run ``graf-report runs=<sweep folder>`` in a fresh
    process (the report is a convenience: a failure is logged, never raised)."""

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        sweep = str(config.hydra.sweep.dir)
        cmd = command("graf-report", f"runs={sweep}", f"hydra.run.dir={sweep}/report_logs")
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
            if p.returncode != 0:
                log.error("graf-report failed on %s: %s", sweep, p.stderr[-2000:])
            else:
                log.info("study report: %s/report.md", sweep)
        except Exception:  # pragma: no cover
            log.exception("could not run graf-report on %s", sweep)
