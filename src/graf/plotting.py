"""Figures of spectra: predicted vs true for a few test ids."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_spectra_grid(
    pred: np.ndarray, target: np.ndarray, ids: np.ndarray, path: str | Path, title: str = "", max_rows: int = 4
) -> Path:
    """One row per id: true spectrum, prediction, absolute error.  Spectra are ``[N, 90, 360]``;
    row r is elevation r+1 deg (drawn upward), column c azimuth c+1 deg."""
    n = min(max_rows, len(ids))
    fig, axes = plt.subplots(n, 3, figsize=(13, 2.0 * n + 0.6), squeeze=False, constrained_layout=True)
    extent = (0.5, 360.5, 0.5, 90.5)
    for r in range(n):
        err = np.abs(pred[r] - target[r])
        psnr = 10 * np.log10(1.0 / max(float(np.mean(err**2)), 1e-10))
        for c, (img, name) in enumerate(((target[r], "true"), (pred[r], "predicted"), (err, "|error|"))):
            ax = axes[r, c]
            im = ax.imshow(
                img, origin="lower", extent=extent, aspect="auto", vmin=0, vmax=1, cmap="magma" if c < 2 else "viridis"
            )
            label = f"id {int(ids[r])}: {name}" + (f" ({psnr:.2f} dB)" if c == 1 else "")
            ax.set_title(label, fontsize=9)
            ax.set_xlabel("azimuth (deg)" if r == n - 1 else "")
            ax.set_ylabel("elevation (deg)" if c == 0 else "")
        fig.colorbar(im, ax=axes[r, :].tolist(), shrink=0.9)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi=80)


def save_figure(fig, path, dpi: int = 80) -> Path:
    """Save a figure atomically (temporary file + rename) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    tmp.replace(path)
    return path
