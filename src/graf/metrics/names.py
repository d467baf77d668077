"""The names of the figures every evaluation reports (``results.json``'s ``metrics``), below everything that
writes or reads them: the pipeline, the sweeps' objectives, the tables."""

from __future__ import annotations

METRIC_NAMES = ("mse", "psnr", "ssim", "lpips")
# <split>/psnr_swapped: PSNR with every target's neighbors replaced by another target's; <split>/reliance_db:
# <split>/psnr minus it (how much a method reads its neighbors; None for a method that takes none)
RELIANCE_NAMES = ("psnr_swapped", "reliance_db")
EVAL_METRICS = tuple(f"{s}/{m}" for s in ("val", "test") for m in METRIC_NAMES) + tuple(
    f"{s}/{m}" for s in ("val", "test") for m in RELIANCE_NAMES
)
