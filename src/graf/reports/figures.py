"""graf-report's figures (PNG), each drawn when its axes vary in the study: the trained-on x test-scene heatmaps,
a metric against a setting (L, the fine-tuned fraction, the survey's spacing), the train band x test band matrix,
and the spectra grids (true and predicted spectra of the same test positions, every method)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import matplotlib.pyplot as plt  # on the Agg backend: graf.plotting (below) sets it
import numpy as np

from graf.io import atomic_write_json
from graf.metrics.names import REGISTRY
from graf.plotting import SPECTRUM_CMAP, SPECTRUM_LABEL, save_figure, shared_limits
from graf.reports.rows import TEST_FIGURES, label_hz, matrices, seed_means, seeds_told, short_scenes

LABELS = {m.label: m for m in REGISTRY.values()}
EXTENT = (0, 360, 0, 90)  # a spectrum's axes in degrees: azimuth 0-360, elevation 0-90


def matrix_figures(rows: list[dict], out: Path) -> dict:
    """Trained-on x test-scene heatmap per method, one figure per metric, each cell the mean over its seeds
    (:func:`~graf.reports.rows.matrices`); returns the matrices (also written to ``matrix.json``)."""
    rows = seed_means(rows)
    mats, written = matrices(rows), []
    methods = list(mats)
    told = seeds_told(r["n_seeds"] for r in rows if r["steps"] != "0")
    for key, name, spec in TEST_FIGURES:
        # one colour scale for every method of the figure (they are compared), one colour bar
        lo, hi = shared_limits([r.get(key) if r.get(key) is not None else np.nan for r in rows])
        n_rows = max(len(mats[m][name]["rows"]) for m in methods)
        fig, axes = plt.subplots(
            1,
            len(methods),
            figsize=(3.2 * len(methods) + 1, 0.6 * n_rows + 2.2),
            squeeze=False,
            constrained_layout=True,
        )
        for ax, m in zip(axes[0], methods):
            cell = mats[m][name]
            M, ev, ylabels = np.array(cell["values"], dtype=float), cell["cols"], cell["rows"]
            im = ax.imshow(
                M, cmap="viridis" if LABELS[name].higher_is_better else "viridis_r", aspect="auto", vmin=lo, vmax=hi
            )
            for (i, j), v in np.ndenumerate(M):
                if not np.isnan(v):
                    ax.text(j, i, spec.format(v), ha="center", va="center", fontsize=7, color=_ink(im, v))
            ax.set_xticks(range(len(ev)), ev, rotation=45, ha="right", fontsize=7)
            ax.set_yticks(range(len(ylabels)), ylabels, fontsize=7)
            ax.set_title(m, fontsize=9)
        reversed_note = "" if LABELS[name].higher_is_better else "\n(map reversed: yellow is better)"
        unit = LABELS[name].axis_label() + reversed_note
        fig.colorbar(im, ax=axes[0].tolist(), shrink=0.9, label=unit)
        fig.suptitle(f"test {name}: trained on (rows) x tested on (columns), {told}; one colour scale")
        path = out / f"matrix_{name.lower()}.png"
        save_figure(fig, path, dpi=110)
        written.append(path.name)
    atomic_write_json(out / "matrix.json", mats)
    return {"figures": written, "matrices": mats}


def _ink(im, value: float) -> str:
    """Black on a light cell of the heatmap ``im``, white on a dark one."""
    r, g, b, _ = im.cmap(im.norm(value))
    return "k" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "w"


CURVE_UNITS = {m.label: m.axis_label("")[1:] for m in REGISTRY.values()}  # "PSNR (dB), higher is better"


def curve_figure(data: dict, xlabel: str, path: Path, title: str) -> None:
    """Each metric against ``xlabel``, one line per method of ``data`` (``{method: {x: {metric: value}}}``), in a
    grid of two columns (legible at page width; as many rows as the registered metrics need), each y axis with
    its unit and which way is better."""
    rows = -(-len(TEST_FIGURES) // 2)
    fig, axes = plt.subplots(rows, 2, figsize=(10, 3.5 * rows), constrained_layout=True, squeeze=False)
    for ax in axes.flat[len(TEST_FIGURES) :]:
        ax.set_visible(False)
    for ax, (_, name, _) in zip(axes.flat, TEST_FIGURES):
        for m, pts in sorted(data.items()):
            xs = list(pts)
            ax.plot(xs, [p[name] for p in pts.values()], "o-", label=m)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(CURVE_UNITS.get(name, name))
        ax.set_title(name)
        ax.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=8)
    fig.suptitle(title)
    save_figure(fig, path, dpi=110)


def band_figure(rows: list[dict], path: Path) -> dict:
    """Train band x test band heatmap of test PSNR per method, one colour scale; returns the matrices."""
    methods = sorted({r["method"] for r in rows})
    tb = sorted({r["train_band"] for r in rows if r["train_band"] not in ("-", "")}, key=label_hz)
    eb = sorted({r["eval_band"] for r in rows}, key=label_hz)
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
    save_figure(fig, path, dpi=110)
    return mats


def spectra_sources(rows: list[dict], runs: Path, axes: list[str], reference: dict) -> dict:
    """``{(test scene, test band): {label: samples file}}``: per method, the saved samples of one job at the
    reference setting of each varied axis (``reference``, conf/report.yaml: ``{L: 10, finetune: f20}``) with
    train band = test band."""
    by_scene = defaultdict(dict)
    for r in rows:
        ok = all(str(r.get(a)) == str(v) for a, v in reference.items() if a in axes and r.get(a) not in (None, "-"))
        if "train_band" in axes and r["train_band"] not in ("-", "") and r["train_band"] != r["eval_band"]:
            ok = False
        f = runs / r["job"] / "samples" / f"{r['eval_scene']}__{r['method']}.npz"
        key = (r["eval_scene"], r["eval_band"])
        label = r["method"] if r["steps"] == "0" else f"{r['method']} ({short_scenes(r['trained_on'])})"
        if ok and f.is_file() and label not in by_scene[key]:
            by_scene[key][label] = f
    return by_scene


def spectra_grids(rows: list[dict], runs: Path, out: Path, axes: list[str], reference: dict) -> list[str]:
    """Per test scene (and band): true and predicted spectra of the same test positions for every method, from
    the jobs of :func:`spectra_sources`; the names of the figures written."""
    written = []
    for (scene, band), files in sorted(spectra_sources(rows, runs, axes, reference).items()):
        data = {m: np.load(f) for m, f in sorted(files.items())}
        first = next(iter(data.values()))
        n = len(first["ids"])
        if n == 0:  # a validation-only job (test=false) saves no test spectra: nothing to show
            continue
        fig, axs = plt.subplots(
            len(data) + 1, n, figsize=(3.6 * n, 1.25 * (len(data) + 1) + 0.6), squeeze=False, constrained_layout=True
        )
        shown = {"origin": "lower", "aspect": "auto", "cmap": SPECTRUM_CMAP, "vmin": 0, "vmax": 1, "extent": EXTENT}
        for j in range(n):
            axs[0, j].imshow(first["target"][j] / 255.0, **shown)
            axs[0, j].set_title(f"id {int(first['ids'][j])}: true", fontsize=8)
            for i, (m, d) in enumerate(data.items(), start=1):
                p, t = d["pred"][j].astype(float) / 255, d["target"][j].astype(float) / 255
                psnr = 10 * np.log10(1.0 / max(float(np.mean((p - t) ** 2)), 1e-10))
                axs[i, j].imshow(d["pred"][j] / 255.0, **shown)
                axs[i, j].set_title(f"{m}: {psnr:.1f} dB", fontsize=7)
        for (i, j), a in np.ndenumerate(axs):  # degrees on the outer axes only
            a.set_xticks([0, 180, 360] if i == len(data) else [])
            a.set_yticks([0, 45, 90] if j == 0 else [])
            a.tick_params(labelsize=6)
        for a in axs[-1]:
            a.set_xlabel("azimuth (°)", fontsize=7)
        for a in axs[:, 0]:
            a.set_ylabel("elevation (°)", fontsize=7)
        fig.colorbar(axs[0, 0].images[0], ax=axs.ravel().tolist(), shrink=0.9, label=SPECTRUM_LABEL)
        fig.suptitle(f"{scene} ({band}): true (top) and predicted spectra, the same test positions")
        path = out / f"spectra_{scene}{'_' + band.replace(' ', '') if 'eval_band' in axes else ''}.png"
        save_figure(fig, path, dpi=100)
        written.append(path.name)
    return written
