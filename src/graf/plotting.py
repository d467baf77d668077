"""Figures of spectra, and the colour scales every figure of the platform shares.

Spectra (true and predicted, any method) are drawn on one scale, normalised power 0-1 in ``SPECTRUM_CMAP``, with a
colour bar; an error map on one scale per figure (0 to the figure's largest error) in ``ERROR_CMAP``; heatmaps
that compare methods (a study's matrices) on one scale per figure across the methods (:func:`shared_limits`).
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

SPECTRUM_CMAP = "magma"  # normalised power in [0, 1]: true and predicted spectra, every method
ERROR_CMAP = "viridis"  # absolute error of a prediction
SPECTRUM_LABEL = "normalised power (0-1)"


def shared_limits(*arrays, low=None, high=None) -> tuple[float, float]:
    """One colour scale for all ``arrays`` (NaN ignored): ``(min, max)``, ``low``/``high`` fixed when given; a
    constant or empty set of values gets a unit-wide range so the colour bar stays drawable."""
    vals = [np.asarray(a, dtype=float).ravel() for a in arrays]
    vals = np.concatenate(vals) if vals else np.array([])
    vals = vals[np.isfinite(vals)]
    lo = float(low) if low is not None else (float(vals.min()) if vals.size else 0.0)
    hi = float(high) if high is not None else (float(vals.max()) if vals.size else 1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    return lo, hi


def plot_spectra_grid(
    pred: np.ndarray, target: np.ndarray, ids: np.ndarray, path: str | Path, title: str = "", max_rows: int = 4
) -> Path:
    """One row per id: true spectrum, prediction, absolute error.  Spectra are ``[N, 90, 360]``;
    row r is elevation r+1 deg (drawn upward), column c azimuth c+1 deg.  True and predicted spectra share one
    scale (0-1, one colour bar); the errors share another (0 to the largest error drawn, one colour bar)."""
    n = min(max_rows, len(ids))
    fig, axes = plt.subplots(n, 3, figsize=(13, 2.0 * n + 0.6), squeeze=False, constrained_layout=True)
    extent = (0.5, 360.5, 0.5, 90.5)
    errs = [np.abs(np.asarray(pred[r], dtype=float) - np.asarray(target[r], dtype=float)) for r in range(n)]
    elo, ehi = shared_limits(*errs, low=0.0)
    spec_im = err_im = None
    for r in range(n):
        err = errs[r]
        psnr = 10 * np.log10(1.0 / max(float(np.mean(err**2)), 1e-10))
        for c, (img, name) in enumerate(((target[r], "true"), (pred[r], "predicted"), (err, "|error|"))):
            ax = axes[r, c]
            lo, hi, cmap = (0.0, 1.0, SPECTRUM_CMAP) if c < 2 else (elo, ehi, ERROR_CMAP)
            im = ax.imshow(img, origin="lower", extent=extent, aspect="auto", vmin=lo, vmax=hi, cmap=cmap)
            spec_im, err_im = (im, err_im) if c < 2 else (spec_im, im)
            label = f"id {int(ids[r])}: {name}" + (f" ({psnr:.2f} dB)" if c == 1 else "")
            ax.set_title(label, fontsize=9)
            ax.set_xlabel("azimuth (deg)" if r == n - 1 else "")
            ax.set_ylabel("elevation (deg)" if c == 0 else "")
    if n:
        fig.colorbar(spec_im, ax=axes[:, :2].ravel().tolist(), shrink=0.9, label=SPECTRUM_LABEL)
        fig.colorbar(err_im, ax=axes[:, 2].tolist(), shrink=0.9, label="|predicted - true|")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, dpi=80)


def save_figure(fig, path, dpi: int = 80) -> Path:
    """Save a figure atomically (temporary file + rename) and close it; every figure of the platform is written here.

    The PNG holds a 256-colour palette (median cut, no dithering; each colour map has 256 levels, so a heatmap
    loses nothing visible), which makes a figure 2-3x smaller than matplotlib's RGBA: a record's figures are
    regenerated often, and every regeneration stays in the repository's history.
    """
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    drawn = io.BytesIO()  # matplotlib's RGBA, in memory: only the palette image is written
    fig.savefig(drawn, dpi=dpi, format="png")
    plt.close(fig)
    with Image.open(drawn) as im:
        palette = im.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.png")
    palette.save(tmp, format="PNG", optimize=True)
    tmp.replace(path)
    return path
