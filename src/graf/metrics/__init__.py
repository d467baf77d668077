"""Metrics on RF spatial spectra ([N, 90, 360] or [N, 1, 90, 360], values in [0, 1]).

- :mod:`.functional`: per-sample MSE / PSNR / SSIM (pure torch, SSIM == scikit-image).
- :mod:`.lpips`: plain-torch LPIPS v0.1 AlexNet with pretrained weights
  (:mod:`.lpips_weights`; install once with ``python -m graf.metrics.lpips_weights``).
- :mod:`.spectrum_metrics`: torchmetrics classes and :func:`spectrum_metrics`.

Importing this package loads no weights; LPIPS weights are read on first use.
The :mod:`.lpips_weights` names are resolved lazily (PEP 562) so that
``python -m graf.metrics.lpips_weights`` does not find that module pre-imported.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .functional import mse_per_sample, psnr_per_sample, ssim_per_sample
from .lpips import lpips_distance
from .spectrum_metrics import SpectrumLPIPS, SpectrumMSE, SpectrumPSNR, SpectrumSSIM, spectrum_metrics

if TYPE_CHECKING:
    from .lpips_weights import LPIPSWeightsInvalid, LPIPSWeightsMissing, fetch_weights, find_weights

__all__ = [
    "lpips_distance",
    "mse_per_sample",
    "psnr_per_sample",
    "ssim_per_sample",
    "SpectrumMSE",
    "SpectrumPSNR",
    "SpectrumSSIM",
    "SpectrumLPIPS",
    "spectrum_metrics",
    "LPIPSWeightsMissing",
    "LPIPSWeightsInvalid",
    "find_weights",
    "fetch_weights",
]

_LAZY = frozenset({"LPIPSWeightsMissing", "LPIPSWeightsInvalid", "find_weights", "fetch_weights"})


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from . import lpips_weights

        value = getattr(lpips_weights, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
