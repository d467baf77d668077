"""graf-curves' outputs after every run: ``curves.md`` and ``curves.csv`` (one row per point), ``results.json`` (the
rows, each regime's KNN line and the failures) and ``curves.png`` (PSNR, SSIM and LPIPS against steps)."""

from __future__ import annotations

from pathlib import Path

from graf.io import atomic_write_json, atomic_write_text
from graf.reports.table import to_csv

COLUMNS = (
    "regime", "method", "step", "val_psnr", "val_ssim", "val_lpips", "val_reliance_db", "fit_s", "s_per_step", "device"
)  # fmt: skip
FIGURES = (("val/psnr", "val_psnr", "PSNR (dB)"), ("val/ssim", "val_ssim", "SSIM"), ("val/lpips", "val_lpips", "LPIPS"))


def _fmt(v, spec):
    return "n/a" if v is None else format(v, spec)


def write_outputs(out: Path, rows: list[dict], knn: dict, failed: list[dict]) -> None:
    lines = [
        "| regime | method | step | val PSNR | val SSIM | val LPIPS | val reliance dB | train s (cum.) | s/step "
        "| device |",
        "|" + "---|" * 10,
    ]
    for r in rows:
        lines.append(
            f"| {r['regime']} | {r['method']} | {r['step']} | {_fmt(r['val_psnr'], '.2f')} | "
            f"{_fmt(r['val_ssim'], '.3f')} | {_fmt(r['val_lpips'], '.3f')} | {_fmt(r['val_reliance_db'], '.2f')} | "
            f"{_fmt(r['fit_s'], '.0f')} | {_fmt(r['s_per_step'], '.3f')} | {r.get('device') or 'n/a'} |"
        )
    for rname, k in knn.items():
        lines.append(
            f"| {rname} | knn (line) | 0 | {_fmt(k['val/psnr'], '.2f')} | {_fmt(k['val/ssim'], '.3f')} | "
            f"{_fmt(k['val/lpips'], '.3f')} | {_fmt(k['val/reliance_db'], '.2f')} | 0 | n/a | n/a |"
        )
    atomic_write_text(out / "curves.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "curves.csv", to_csv(COLUMNS, [[r[c] for c in COLUMNS] for r in rows]))
    atomic_write_json(out / "results.json", {"task": "curves", "rows": rows, "knn": knn, "failed": failed})
    if rows or knn:
        plot(out / "curves.png", rows, knn)


def plot(path: Path, rows: list[dict], knn: dict) -> None:
    """PSNR, SSIM and LPIPS against steps on a log axis, one row of panels per regime, KNN as a dashed line."""
    # lazy: pyplot adds about 0.4 s to the command's start-up, and only the figure needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    regimes = sorted({r["regime"] for r in rows} | set(knn))
    # one colour per method in every panel, so a method reads the same across regimes
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colour = {m: cycle[k % len(cycle)] for k, m in enumerate(sorted({r["method"] for r in rows}))}
    fig, axes = plt.subplots(
        len(regimes), len(FIGURES), figsize=(13, 3.3 * len(regimes)), squeeze=False, constrained_layout=True
    )
    for i, rname in enumerate(regimes):
        for j, (key, col, label) in enumerate(FIGURES):
            ax = axes[i][j]
            for m in sorted({r["method"] for r in rows if r["regime"] == rname}):
                pts = [
                    (r["step"], r[col])
                    for r in rows
                    if r["regime"] == rname and r["method"] == m and r[col] is not None
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
    fig.savefig(path, dpi=110)
    plt.close(fig)
