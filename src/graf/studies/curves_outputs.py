"""graf-curves' outputs after every run: ``curves.md`` and ``curves.csv`` (one row per point), ``results.json`` (the
rows, each regime's KNN line and the failures) and ``curves.png`` (each metric on the curves against steps: PSNR,
SSIM, LPIPS and any a plugin registers; :func:`graf.metrics.names.curve_metrics`)."""

from __future__ import annotations

from pathlib import Path

from graf.io import atomic_write_json, atomic_write_text
from graf.metrics.names import curve_metrics
from graf.reports.table import to_csv


def columns() -> tuple[str, ...]:
    """``curves.csv``'s columns: one ``val_<name>`` per metric on the curves (:func:`curve_metrics`, a plugin's
    included), then the reliance and the cost."""
    figures = tuple(f"val_{m.name}" for m in curve_metrics())
    return ("regime", "method", "step", *figures, "val_reliance_db", "fit_s", "s_per_step", "device")


def figures() -> tuple[tuple[str, str, str], ...]:
    """``(val/<name>, val_<name>, label with unit)`` of each metric on the curves: a panel each in ``curves.png``."""
    return tuple(
        (f"val/{m.name}", f"val_{m.name}", f"{m.label} ({m.unit})" if m.unit else m.label) for m in curve_metrics()
    )


def _fmt(v, spec):
    return "n/a" if v is None else spec.format(v)


def write_outputs(out: Path, rows: list[dict], knn: dict, failed: list[dict]) -> None:
    metrics = curve_metrics()
    header = ["regime", "method", "step", *(f"val {m.label}" for m in metrics), "val reliance dB", "train s (cum.)"]
    lines = ["| " + " | ".join([*header, "s/step", "device"]) + " |", "|" + "---|" * (len(header) + 2)]
    for r in rows:
        cells = [r["regime"], r["method"], r["step"], *(_fmt(r.get(f"val_{m.name}"), m.fmt) for m in metrics)]
        cells += [_fmt(r["val_reliance_db"], "{:.2f}"), _fmt(r["fit_s"], "{:.0f}"), _fmt(r["s_per_step"], "{:.3f}")]
        lines.append("| " + " | ".join(map(str, [*cells, r.get("device") or "n/a"])) + " |")
    for rname, k in knn.items():
        cells = [rname, "knn (line)", 0, *(_fmt(k.get(f"val/{m.name}"), m.fmt) for m in metrics)]
        lines.append(
            "| " + " | ".join(map(str, [*cells, _fmt(k.get("val/reliance_db"), "{:.2f}"), 0, "n/a", "n/a"])) + " |"
        )
    cols = columns()
    atomic_write_text(out / "curves.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "curves.csv", to_csv(cols, [[r.get(c) for c in cols] for r in rows]))
    atomic_write_json(out / "results.json", {"task": "curves", "rows": rows, "knn": knn, "failed": failed})
    if rows or knn:
        plot(out / "curves.png", rows, knn)


def plot(path: Path, rows: list[dict], knn: dict) -> None:
    """PSNR, SSIM and LPIPS against steps on a log axis, one row of panels per regime, KNN as a dashed line."""
    # lazy: pyplot adds about 0.4 s to the command's start-up, and only the figure needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from graf.plotting import save_figure

    regimes = sorted({r["regime"] for r in rows} | set(knn))
    # one colour per method in every panel, so a method reads the same across regimes
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colour = {m: cycle[k % len(cycle)] for k, m in enumerate(sorted({r["method"] for r in rows}))}
    panels = figures()
    fig, axes = plt.subplots(
        len(regimes), len(panels), figsize=(13, 3.3 * len(regimes)), squeeze=False, constrained_layout=True
    )
    for i, rname in enumerate(regimes):
        for j, (key, col, label) in enumerate(panels):
            ax = axes[i][j]
            for m in sorted({r["method"] for r in rows if r["regime"] == rname}):
                pts = [
                    (r["step"], r[col])
                    for r in rows
                    if r["regime"] == rname and r["method"] == m and r.get(col) is not None
                ]
                if pts:
                    ax.plot(*zip(*pts), marker="o", label=m, color=colour[m])
            if rname in knn and knn[rname].get(key) is not None:
                ax.axhline(knn[rname][key], color="k", ls="--", lw=1, label="knn")
            ax.set_xscale("log")
            ax.set_xlabel("training steps")
            ax.set_ylabel(f"validation {label}")
            ax.set_title(rname)
            ax.grid(alpha=0.3)
        axes[i][0].legend(fontsize=8)
    save_figure(fig, path, dpi=110)
