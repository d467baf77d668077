"""graf-report: the tables and figures of a study folder.

    graf-report runs=multirun/cross_scene_matrix [out=sweeps/cross_scene_matrix]

Reads every ``results.json`` under ``runs`` (the models a study trains first, under ``base/`` folders, are
left out: their figures are the study's jobs' starting points, not its results) and writes into ``out``
(default: ``runs``):

- ``rows.csv`` / ``rows.json``: one row per (job, test scene, method), baselines tested inside a job
  included (once where several jobs tested the same baseline on the same data);
- ``report.md``, ``report.csv``, ``report.tex``: method x metric (MSE, LPIPS, PSNR, SSIM; the seed's
  tables) with the number of test spectra and the training budget (steps), one block per setting that
  varies in the study (trained on, train band, fine-tuning, L, test scene, test band);
- figures (PNG), each when its axes vary in the study: ``matrix_<metric>.png`` (trained-on x test-scene
  heatmap per method), ``vs_L.png`` (metric vs neighbor count, averaged over the same-family pairs:
  conference_v1 -> v2/v3 and office_v1 -> v2/v3), ``vs_fraction.png`` (metric vs fine-tuned fraction per
  test scene; zero-shot at 0), ``band_matrix.png`` (train band x test band per method), and
  ``spectra_<scene>.png``: the same test positions, true and predicted by every method (from the jobs'
  ``samples/``, ``save_samples=N``).

A study's multirun calls it when it ends (:class:`StudyReport`, a Hydra callback); it is also this command.
"""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from graf.errors import ConfigError
from graf.io import atomic_write_bytes, atomic_write_json
from graf.plotting import SPECTRUM_CMAP, SPECTRUM_LABEL, shared_limits
from graf.run.config import family, task_wrapper
from graf.studies.table import read_run_result, to_csv
from graf.studies.table import to_markdown as table_markdown

log = logging.getLogger("graf")

# neighbor reliance (PSNR with true minus with swapped neighbors): a column of the tables, not a figure
RELIANCE = ("test/reliance_db", "reliance dB", "{:.2f}")
METRICS = (
    ("test/mse", "MSE", "{:.4f}"),
    ("test/lpips", "LPIPS", "{:.3f}"),
    ("test/psnr", "PSNR", "{:.2f}"),
    ("test/ssim", "SSIM", "{:.3f}"),
)
# the settings a study may vary, in the order its table blocks are nested
AXES = ("trained_on", "train_band", "finetune", "L", "eval_scene", "eval_band")
REFERENCE = {"L": 10, "finetune": "f20"}  # which job of a varied axis the spectra grids show


def _band(hz) -> str:
    if hz is None:
        return ""
    hz = float(hz)
    return f"{hz / 1e9:g} GHz" if hz >= 1e9 else f"{hz / 1e6:g} MHz"


def _ft_label(ft: dict | None) -> str:
    if not ft:
        return "-"
    if ft.get("mode") == "zero-shot":
        return "zero-shot"
    return f"f{round(100 * float(ft.get('fraction') or 1.0)):02d}"


def _measured(result: dict) -> float | None:
    f = (result.get("splits") or {}).get("measured_fraction")
    return None if f is None else float(f)


def _ft_fraction(label: str) -> float | None:
    if label == "zero-shot":
        return 0.0
    if label.startswith("f") and label[1:].isdigit():
        return int(label[1:]) / 100.0
    return None


def result_files(runs: Path) -> list[Path]:
    if not runs.exists():
        raise ConfigError(f"graf-report: {runs} does not exist")
    if runs.is_file():
        files = [runs]
    else:  # runs may be one run's own folder: its results.json counts
        files = [f for f in sorted(runs.rglob("results.json")) if "base" not in f.relative_to(runs).parts[:-1]]
    if not files:
        raise ConfigError(f"graf-report: no results.json under {runs} (base/ folders are left out)")
    return files


def rows_of(result: dict, job: str) -> list[dict]:
    """One row per (test scene, method) of a job's results.json."""
    cfg = result.get("config") or {}
    ft = result.get("finetune")
    if ft and ft.get("base_scenes"):
        trained = sorted(ft["base_scenes"], key=lambda n: ft["base_scenes"][n]["index"])
        train_hz = sorted({float(v["band_hz"]) for v in ft["base_scenes"].values() if v.get("band_hz")})
    else:
        trained, train_hz = (
            list(result.get("train_scenes") or [result.get("scene")]),
            sorted(set(result.get("train_bands_hz") or [result.get("band_hz")])),
        )
    steps = int(result.get("global_step") or 0)
    budget = f"{steps}" if not ft else f"{ft.get('base_steps', '?')}+{ft.get('steps', 0)}"
    common = {
        "job": job,
        "trained_on": "+".join(trained),
        "train_band": " + ".join(_band(h) for h in train_hz),
        # a fine-tuning run's fraction, or a from-scratch run's on a measured fraction (the density study)
        "finetune": _ft_label(ft) if ft or _measured(result) is None else f"f{round(100 * _measured(result)):02d}",
        "test_pool": (ft or {}).get("test_pool", ""),
        "L": (cfg.get("neighbors") or {}).get("L"),
        # the survey's density: median nearest-neighbor distance of the measured training positions (m)
        "spacing_m": (result.get("splits") or {}).get("measured_spacing_m"),
    }
    evals = result.get("evaluations") or [
        {
            "eval_scene": result.get("eval_scene") or result.get("scene"),
            "within_scene": result.get("within_scene", True),
            "metrics": result.get("metrics", {}),
            "n_test": result.get("n_test"),
            "band_hz": result.get("band_hz"),
            "baselines": result.get("baselines"),
        }
    ]
    out = []
    for ev in evals:
        base = {
            **common,
            "eval_scene": ev["eval_scene"],
            "eval_band": _band(ev.get("band_hz")),
            "within_scene": bool(ev.get("within_scene")),
            "n_test": ev.get("n_test"),
        }
        out.append(
            {
                **base,
                "method": result.get("method"),
                "steps": budget,
                **{k: (ev.get("metrics") or {}).get(k) for k, _, _ in (*METRICS, RELIANCE)},
            }
        )
        for name, b in (ev.get("baselines") or {}).items():
            # a baseline is not trained: it is the same whatever the job trained on
            out.append(
                {
                    **base,
                    "trained_on": "-",
                    "train_band": "-",
                    "within_scene": None,
                    "method": name,
                    "steps": "0",
                    **{k: (b.get("metrics") or {}).get(k) for k, _, _ in (*METRICS, RELIANCE)},
                }
            )
    return out


def collect_rows(runs: Path) -> tuple[list[dict], list[Path]]:
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


def varying_axes(rows: list[dict]) -> list[str]:
    return [
        a
        for a in AXES
        if len({str(r.get(a)) for r in rows if r["steps"] != "0" or a not in ("trained_on", "train_band")}) > 1
    ]


def _sort_key(v):
    if isinstance(v, (int, float)):
        return (0, v, "")
    f = _ft_fraction(str(v)) if isinstance(v, str) else None
    return (0, f, "") if f is not None else (1, 0, str(v))


def table(rows: list[dict], axes: list[str]) -> tuple[list[str], list[list]]:
    """Method x metric rows, sorted by the study's varying axes (the seed's tables: one block per setting)."""
    header = [*axes, "method", "n_test", "steps", *[n for _, n, _ in (*METRICS, RELIANCE)]]
    order = sorted(rows, key=lambda r: ([_sort_key(r.get(a)) for a in axes], r["method"] == "knn", r["method"]))
    return header, [
        [r.get(a) for a in axes]
        + [r["method"], r.get("n_test"), r["steps"]]
        + [r.get(k) for k, _, _ in (*METRICS, RELIANCE)]
        for r in order
    ]


def _fmt(v, col: str) -> str:
    spec = {n: s for _, n, s in (*METRICS, RELIANCE)}.get(col)
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
        r"\begin{tabular}{" + "l" * (len(header) - len(METRICS) - 1) + "r" * (len(METRICS) + 1) + "}",
        r"\toprule",
        " & ".join(esc(h) for h in header) + r" \\",
        r"\midrule",
    ]
    lines += [" & ".join(esc(_fmt(v, c)) for v, c in zip(row, header)) + r" \\" for row in body]
    return "\n".join(lines + [r"\bottomrule", r"\end{tabular}"]) + "\n"


def mean(values) -> float | None:
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(v)) if v else None


# ---------------------------------------------------------------------- figures
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def matrix_figures(rows: list[dict], out: Path) -> dict:
    """Trained-on x test-scene heatmap per method, one figure per metric; returns the matrices."""
    plt = _plt()
    trained = [r for r in rows if r["steps"] != "0"]
    methods = sorted({r["method"] for r in trained}) + sorted({r["method"] for r in rows if r["steps"] == "0"})
    tr = sorted({r["trained_on"] for r in trained})
    ev = sorted({r["eval_scene"] for r in rows})
    mats, written = {}, []
    for key, name, spec in METRICS:
        # one colour scale for every method of the figure (they are compared), one colour bar
        lo, hi = shared_limits([r.get(key) if r.get(key) is not None else np.nan for r in rows])
        fig, axes = plt.subplots(
            1,
            len(methods),
            figsize=(3.2 * len(methods) + 1, 0.6 * len(tr) + 2.2),
            squeeze=False,
            constrained_layout=True,
        )
        for ax, m in zip(axes[0], methods):
            baseline = all(r["steps"] == "0" for r in rows if r["method"] == m)
            ylabels = ["(no training)"] if baseline else tr
            M = np.full((len(ylabels), len(ev)), np.nan)
            for r in rows:
                if r["method"] != m:
                    continue
                i = 0 if baseline else tr.index(r["trained_on"])
                M[i, ev.index(r["eval_scene"])] = r.get(key) if r.get(key) is not None else np.nan
            mats.setdefault(m, {})[name] = {"rows": ylabels, "cols": ev, "values": M.tolist()}
            im = ax.imshow(
                M, cmap="viridis_r" if name in ("MSE", "LPIPS") else "viridis", aspect="auto", vmin=lo, vmax=hi
            )
            for (i, j), v in np.ndenumerate(M):
                if not np.isnan(v):
                    ax.text(j, i, spec.format(v), ha="center", va="center", fontsize=7, color="w")
            ax.set_xticks(range(len(ev)), ev, rotation=45, ha="right", fontsize=7)
            ax.set_yticks(range(len(ylabels)), ylabels, fontsize=7)
            ax.set_title(m, fontsize=9)
        fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label=f"test {name} (one scale for every method)")
        fig.suptitle(f"test {name}: trained on (rows) x tested on (columns)")
        path = out / f"matrix_{name.lower()}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path.name)
    atomic_write_json(out / "matrix.json", mats)
    return {"figures": written, "matrices": mats}


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
        out[m][x] = {name: mean(r.get(k) for r in rs) for k, name, _ in METRICS} | {"n_pairs": len(rs)}
    return {m: dict(sorted(v.items(), key=lambda kv: _sort_key(kv[0]))) for m, v in out.items()}


PSNR_TARGETS = (16.0, 18.0, 20.0, 22.0, 25.0)  # dB: "how densely must I measure for X dB?"


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


def curve_figure(data: dict, xlabel: str, path: Path, title: str) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, len(METRICS), figsize=(16, 3.4), constrained_layout=True)
    for ax, (_, name, _) in zip(axes, METRICS):
        for m, pts in sorted(data.items()):
            xs = list(pts)
            ax.plot(xs, [p[name] for p in pts.values()], "o-", label=m)
        ax.set_xlabel(xlabel)
        ax.set_title(name)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def band_figure(rows: list[dict], path: Path) -> dict:
    plt = _plt()
    methods = sorted({r["method"] for r in rows})
    tb = sorted({r["train_band"] for r in rows if r["train_band"] not in ("-", "")}, key=_band_hz)
    eb = sorted({r["eval_band"] for r in rows}, key=_band_hz)
    fig, axes = plt.subplots(1, len(methods), figsize=(4.2 * len(methods), 3.6), squeeze=False, constrained_layout=True)
    mats, im = {}, None
    lo, hi = shared_limits([r.get("test/psnr") if r.get("test/psnr") is not None else np.nan for r in rows])
    for ax, m in zip(axes[0], methods):
        rs = [r for r in rows if r["method"] == m]
        ylabels = tb if any(r["train_band"] not in ("-", "") for r in rs) else ["(no training)"]
        M = np.full((len(ylabels), len(eb)), np.nan)
        for r in rs:
            i = ylabels.index(r["train_band"]) if r["train_band"] in ylabels else 0
            M[i, eb.index(r["eval_band"])] = r.get("test/psnr") if r.get("test/psnr") is not None else np.nan
        mats[m] = {"rows": ylabels, "cols": eb, "psnr": M.tolist()}
        im = ax.imshow(M, cmap="viridis", aspect="auto", vmin=lo, vmax=hi)
        for (i, j), v in np.ndenumerate(M):
            if not np.isnan(v):
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=8, color="w")
        ax.set_xticks(range(len(eb)), eb, fontsize=8)
        ax.set_yticks(range(len(ylabels)), ylabels, fontsize=8)
        ax.set_xlabel("test band")
        ax.set_ylabel("train band")
        ax.set_title(f"{m}: test PSNR (dB)", fontsize=9)
    if im is not None:
        fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="test PSNR (dB), one scale for every method")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return mats


def _band_hz(label: str) -> float:
    try:
        v, unit = label.split()
        return float(v) * (1e9 if unit == "GHz" else 1e6)
    except ValueError:
        return 0.0


def spectra_grids(rows: list[dict], runs: Path, out: Path, axes: list[str]) -> list[str]:
    """Per test scene (and band): true and predicted spectra of the same test positions for every method, from
    one job per method at the reference setting of each varied axis (L = 10, 20% fine-tuning, train band =
    test band)."""
    plt = _plt()
    written = []
    by_scene = defaultdict(dict)
    for r in rows:
        ok = all(str(r.get(a)) == str(v) for a, v in REFERENCE.items() if a in axes and r.get(a) not in (None, "-"))
        if "train_band" in axes and r["train_band"] not in ("-", "") and r["train_band"] != r["eval_band"]:
            ok = False
        f = runs / r["job"] / "samples" / f"{r['eval_scene']}__{r['method']}.npz"
        key = (r["eval_scene"], r["eval_band"])
        label = r["method"] if r["steps"] == "0" else f"{r['method']} ({r['trained_on']})"
        if ok and f.is_file() and label not in by_scene[key]:
            by_scene[key][label] = f
    for (scene, band), files in sorted(by_scene.items()):
        data = {m: np.load(f) for m, f in sorted(files.items())}
        first = next(iter(data.values()))
        n = len(first["ids"])
        fig, axs = plt.subplots(
            len(data) + 1, n, figsize=(3.6 * n, 1.25 * (len(data) + 1) + 0.6), squeeze=False, constrained_layout=True
        )
        for j in range(n):
            axs[0, j].imshow(
                first["target"][j] / 255.0, origin="lower", aspect="auto", cmap=SPECTRUM_CMAP, vmin=0, vmax=1
            )
            axs[0, j].set_title(f"id {int(first['ids'][j])}: true", fontsize=8)
            for i, (m, d) in enumerate(data.items(), start=1):
                p, t = d["pred"][j].astype(float) / 255, d["target"][j].astype(float) / 255
                psnr = 10 * np.log10(1.0 / max(float(np.mean((p - t) ** 2)), 1e-10))
                axs[i, j].imshow(
                    d["pred"][j] / 255.0, origin="lower", aspect="auto", cmap=SPECTRUM_CMAP, vmin=0, vmax=1
                )
                axs[i, j].set_title(f"{m}: {psnr:.1f} dB", fontsize=7)
        for a in axs.flat:
            a.set_xticks([]), a.set_yticks([])
        fig.colorbar(axs[0, 0].images[0], ax=axs.ravel().tolist(), shrink=0.9, label=SPECTRUM_LABEL)
        fig.suptitle(f"{scene} ({band}): true (top) and predicted spectra, the same test positions")
        path = out / f"spectra_{scene}{'_' + band.replace(' ', '') if 'eval_band' in axes else ''}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path.name)
    return written


# ---------------------------------------------------------------------- the command
def make_report(runs: Path, out: Path) -> dict:
    rows, files = collect_rows(runs)
    out.mkdir(parents=True, exist_ok=True)
    axes = varying_axes(rows)
    header, body = table(rows, axes)
    atomic_write_bytes(out / "report.md", to_markdown(header, body).encode())
    atomic_write_bytes(out / "report.csv", to_csv(header, body).encode())
    atomic_write_bytes(out / "report.tex", to_latex(header, body).encode())
    cols = ["job", *AXES, "within_scene", "test_pool", "method", "n_test", "steps", *[k for k, _, _ in METRICS]]
    atomic_write_bytes(out / "rows.csv", to_csv(cols, [[r.get(c) for c in cols] for r in rows]).encode())
    summary = {"runs": str(runs), "n_results": len(files), "n_rows": len(rows), "axes": axes, "figures": []}
    if "L" in axes:
        data = curve(rows, "L", same_family=True)
        curve_figure(data, "neighbors L at test", out / "vs_L.png", "metric vs L (mean over same-family test pairs)")
        summary["vs_L"] = data
        summary["figures"].append("vs_L.png")
    if "finetune" in axes:
        summary["vs_fraction"] = {}
        for key in sorted({(r["eval_scene"], r["train_band"]) for r in rows if r["steps"] != "0"}):
            sub = [r for r in rows if r["eval_scene"] == key[0] and r["train_band"] in (key[1], "-")]
            data = curve([{**r, "fraction": _ft_fraction(r["finetune"])} for r in sub], "fraction", False)
            name = f"vs_fraction_{key[0]}_{key[1].replace(' ', '')}.png"
            curve_figure(
                data,
                "fraction of the new scene's training split (0: zero-shot)",
                out / name,
                f"{key[0]}: metric vs fine-tuned fraction (models trained at {key[1]})",
            )
            summary["vs_fraction"][f"{key[0]} | trained at {key[1]}"] = data
            summary["figures"].append(name)
    if (
        "finetune" in axes
        and any(r.get("spacing_m") for r in rows)
        and not any(r["within_scene"] is False for r in rows)
    ):
        # a density study (methods trained on thinned surveys of the scene they are tested on): metric vs spacing
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
    if "eval_band" in axes and "train_band" in axes and "eval_scene" not in axes and "finetune" not in axes:
        # a band x band matrix of one layout (bands); not when the band changes with the test scene
        summary["band_matrix"] = band_figure(rows, out / "band_matrix.png")
        summary["figures"].append("band_matrix.png")
    elif "eval_scene" in axes and "trained_on" in axes and "L" not in axes and "finetune" not in axes:
        m = matrix_figures(rows, out)
        summary["matrix"] = m["matrices"]
        summary["figures"] += m["figures"]
    summary["figures"] += spectra_grids(rows, runs, out, axes)
    atomic_write_json(out / "rows.json", {"rows": rows})
    atomic_write_json(out / "report.json", summary)
    return summary


@task_wrapper
def report(cfg: DictConfig) -> dict:
    runs = Path(str(cfg.runs))
    out = Path(str(cfg.out)) if cfg.get("out") else runs
    summary = make_report(runs, out)
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
        cmd = [sys.executable, "-m", "graf.cli.report", f"runs={sweep}", f"hydra.run.dir={sweep}/report_logs"]
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
            if p.returncode != 0:
                log.error("graf-report failed on %s: %s", sweep, p.stderr[-2000:])
            else:
                log.info("study report: %s/report.md", sweep)
        except Exception:  # pragma: no cover
            log.exception("could not run graf-report on %s", sweep)
