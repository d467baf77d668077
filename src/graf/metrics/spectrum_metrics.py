"""torchmetrics wrappers: dataset-level means of per-spectrum MSE / PSNR / SSIM / LPIPS.

Each metric keeps two states, ``total`` (sum of per-spectrum values; float64, or
float32 on devices without float64 such as MPS) and ``count`` (int64), both
reduced with ``sum`` across processes; ``compute()`` returns ``total / count``
(float32), i.e. the mean over every spectrum seen -- not a mean of batch means.
"""

from __future__ import annotations

import importlib
import inspect
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric, MetricCollection

from graf.errors import PluginError
from graf.plugins import call_registered, registered

from .functional import mse_per_sample, psnr_per_sample, ssim_per_sample
from .lpips import get_lpips_model, lpips_distance
from .names import REGISTRY, check_metric_names
from .names import Metric as RegisteredMetric

__all__ = [
    "EmptyTargets",
    "empty_targets",
    "SpectrumMSE",
    "SpectrumPSNR",
    "SpectrumSSIM",
    "SpectrumLPIPS",
    "spectrum_metrics",
]


def _acc_dtype(device: torch.device) -> torch.dtype:
    return torch.float32 if device.type == "mps" else torch.float64


def _check_spectra(metric: str, pred: Tensor, target: Tensor) -> None:
    for name, x in (("pred", pred), ("target", target)):
        if not isinstance(x, Tensor):
            raise TypeError(f"{metric}.update: {name} must be a torch.Tensor, got {type(x).__name__}")
        if not (x.ndim == 3 or (x.ndim == 4 and x.shape[1] == 1)):
            raise ValueError(f"{metric}.update: {name} must have shape [N, H, W] or [N, 1, H, W], got {tuple(x.shape)}")


def empty_targets(target: Tensor) -> Tensor:
    """``[N]`` bool: the targets with no path (every pixel 0: a transmitter no ray reaches, e.g. 5.7% of the outdoor
    scene's positions).  The policy: such a target is left out of every metric's mean and counted
    (``<split>/n_empty``); its per-spectrum values are NaN.  Scored, every method predicts it exactly and PSNR's
    100 dB cap would add about 0.6 dB to a scene's mean per empty spectrum in 120."""
    return target.reshape(target.shape[0], -1).amax(dim=1) <= 0


class EmptyTargets(Metric):
    """How many targets were empty (:func:`empty_targets`): left out of the other metrics' means."""

    full_state_update = False
    is_differentiable = False
    higher_is_better = None
    count: Tensor

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.add_state("count", default=torch.zeros((), dtype=torch.int64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor) -> None:
        _check_spectra(type(self).__name__, pred, target)
        self.count = self.count + int(empty_targets(target).sum())

    def compute(self) -> Tensor:
        return self.count.to(torch.float32)


class _SpectrumMean(Metric):
    """Mean over all spectra of a per-spectrum value; subclasses define :meth:`_per_sample`."""

    full_state_update = False
    is_differentiable = False
    higher_is_better: bool | None = None

    total: Tensor
    count: Tensor

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.add_state("total", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.zeros((), dtype=torch.int64), dist_reduce_fx="sum")

    def _per_sample(self, pred: Tensor, target: Tensor) -> Tensor:
        raise NotImplementedError

    def update(self, pred: Tensor, target: Tensor) -> None:
        """Add a batch of spectra ``[N, H, W]`` or ``[N, 1, H, W]`` with values in [0, 1].  An empty target
        (:func:`empty_targets`) is left out of the mean: its value is NaN in :attr:`last_values`."""
        _check_spectra(type(self).__name__, pred, target)
        keep = ~empty_targets(target)
        values = torch.full((target.shape[0],), float("nan"), dtype=torch.float64, device=target.device)
        if bool(keep.any()):
            values[keep] = self._per_sample(pred[keep], target[keep]).to(torch.float64)
        self.last_values = values.detach()  # the batch's per-spectrum values (per-spectrum records)
        # out-of-place: works whether states/inputs were created inside or outside inference_mode
        self.total = self.total + values[keep].to(device=self.total.device, dtype=self.total.dtype).sum()
        self.count = self.count + int(keep.sum())

    def compute(self) -> Tensor:
        """The mean over the non-empty spectra seen (NaN when there were none)."""
        if int(self.count) == 0:
            return torch.tensor(float("nan"))
        return (self.total / self.count).to(torch.float32)

    def _apply(self, fn: Callable, exclude_state: Sequence[str] = "") -> Any:
        # torchmetrics applies ``fn`` to the states too, so ``module.to(torch.bfloat16)`` (e.g.
        # Lightning "bf16-true") would silently turn the float64 accumulator into bf16, and
        # ``.to("mps")`` would fail on it. Move ``total`` ourselves: follow the device only and
        # keep the accumulator dtype.
        excl = (exclude_state,) if isinstance(exclude_state, str) else tuple(exclude_state)
        this = super()._apply(fn, exclude_state=(*excl, "total"))
        if "total" not in excl:
            device = fn(torch.zeros(1, device=this.total.device)).device
            dtype = _acc_dtype(device)
            this.total = this.total.to(dtype=dtype).to(device=device)
            this._defaults["total"] = this._defaults["total"].to(dtype=dtype).to(device=device)
        return this


class SpectrumMSE(_SpectrumMean):
    """Mean per-spectrum MSE (lower is better)."""

    higher_is_better = False
    plot_lower_bound = 0.0

    def _per_sample(self, pred: Tensor, target: Tensor) -> Tensor:
        return mse_per_sample(pred, target)


class SpectrumPSNR(_SpectrumMean):
    """Mean per-spectrum PSNR in dB (each capped at 100 dB for data_range = 1; higher is better).

    Note: this is the mean of per-spectrum PSNRs, not the PSNR of the pooled MSE.
    """

    higher_is_better = True

    def __init__(self, data_range: float = 1.0, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.data_range = float(data_range)

    def _per_sample(self, pred: Tensor, target: Tensor) -> Tensor:
        return psnr_per_sample(pred, target, data_range=self.data_range)


class SpectrumSSIM(_SpectrumMean):
    """Mean per-spectrum SSIM (skimage Gaussian convention; higher is better)."""

    higher_is_better = True
    plot_upper_bound = 1.0

    def __init__(self, data_range: float = 1.0, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.data_range = float(data_range)

    def _per_sample(self, pred: Tensor, target: Tensor) -> Tensor:
        return ssim_per_sample(pred, target, data_range=self.data_range)


class SpectrumLPIPS(_SpectrumMean):
    """Mean per-spectrum LPIPS v0.1 AlexNet distance (spectra repeated to RGB; lower is better).

    The AlexNet is *not* a submodule: it lives in a process-wide cache (one copy per
    weight file and device, created lazily on the device of the inputs), so a
    LightningModule owning this metric has no LPIPS weights in its ``state_dict``
    and ``.to(device)`` does not copy them. The weights are loaded (and hash-checked)
    at construction so that a missing file fails before training, not at test time.
    """

    higher_is_better = False
    plot_lower_bound = 0.0

    def __init__(self, weights_path: str | os.PathLike[str] | None = None, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.weights_path = None if weights_path is None else str(Path(weights_path).expanduser())
        get_lpips_model("cpu", self.weights_path)  # fail fast: LPIPSWeightsMissing / LPIPSWeightsInvalid

    def _per_sample(self, pred: Tensor, target: Tensor) -> Tensor:
        if pred.ndim == 3:
            pred, target = pred.unsqueeze(1), target.unsqueeze(1)
        return lpips_distance(pred, target, weights_path=self.weights_path)


class RegisteredMean(_SpectrumMean):
    """The mean of a registered metric's per-spectrum function (:class:`graf.metrics.names.Metric`
    ``per_spectrum``) over the non-empty spectra seen.  A plugin's function that raises, or returns anything but
    one value per spectrum (``[N]``: a ``[N, 1]`` or a scalar would be broadcast into wrong values), stops the run
    with one line naming the metric and its plugin module (:func:`graf.plugins.call_registered`)."""

    def __init__(self, metric: RegisteredMetric, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.fn = metric.per_spectrum  # (its direction: the registry's, read by the reports)
        self.metric_name = metric.name

    def _per_sample(self, pred: Tensor, target: Tensor) -> Tensor:
        if pred.ndim == 4:
            pred, target = pred[:, 0], target[:, 0]
        what = f"metric {self.metric_name!r}"
        values = call_registered(what, self.fn, pred, target)
        n = int(pred.shape[0])
        shape = tuple(values.shape) if isinstance(values, Tensor) else None
        if shape != (n,):
            got = f"shape {list(shape)}" if shape is not None else f"a {type(values).__name__}"
            raise PluginError(
                f"{registered(what, self.fn)}: per_spectrum returned {got} for {n} spectra of shape "
                f"{list(pred.shape)}; it must return a tensor of shape [{n}], one value per spectrum"
            )
        return values


def _build(metric: RegisteredMetric, data_range: float) -> Metric:
    if metric.per_spectrum is not None:
        return RegisteredMean(metric)
    cls = getattr(importlib.import_module(metric.factory.rpartition(".")[0]), metric.factory.rpartition(".")[2])
    return cls(data_range=data_range) if "data_range" in inspect.signature(cls).parameters else cls()


def spectrum_metrics(prefix: str = "", *, lpips: bool = True, data_range: float = 1.0) -> MetricCollection:
    """MetricCollection of every registered metric (:data:`graf.metrics.names.REGISTRY`: ``mse``, ``psnr``,
    ``ssim``, ``lpips`` and any registered since; ``lpips=False`` leaves LPIPS out) and ``n_empty``.

    With ``prefix="test/"``, ``compute()`` returns ``{"test/mse", "test/psnr", "test/ssim", "test/lpips", ...}``.
    Compute groups are disabled on purpose: the metrics have identically named states, and torchmetrics would
    otherwise merge metrics whose states happen to coincide after the first batch (e.g. MSE and LPIPS both 0 on
    identical spectra) and then report one metric's value under the other's name.
    """
    metrics: dict[str, Metric] = {
        name: _build(m, data_range) for name, m in REGISTRY.items() if lpips or name != "lpips"
    }
    metrics["n_empty"] = EmptyTargets()
    check_metric_names(metrics)
    return MetricCollection(metrics, prefix=prefix, compute_groups=False)
