"""Per-sample image metrics for RF spatial spectra, pure torch.

Inputs are float tensors ``[N, H, W]`` or ``[N, 1, H, W]`` (spectra are 90x360)
with values nominally in ``[0, 1]``. Every function returns a float32 tensor of
shape ``[N]`` on the inputs' device. Whatever the input dtype (bf16/fp16/fp32/fp64),
the computation runs in float64 (float32 on devices without float64, e.g. MPS)
with autocast disabled.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Iterator

import torch
from torch import Tensor

__all__ = ["mse_per_sample", "psnr_per_sample", "ssim_per_sample", "MSE_FLOOR"]

#: PSNR uses ``max(mse, MSE_FLOOR)``: identical images give 10*log10(data_range**2 / 1e-10)
#: (= 100 dB for data_range = 1) instead of +inf.
MSE_FLOOR = 1e-10

# SSIM constants, scikit-image convention (Wang et al. 2004).
_K1 = 0.01
_K2 = 0.03
_SIGMA = 1.5
_TRUNCATE = 3.5
_RADIUS = int(_TRUNCATE * _SIGMA + 0.5)  # 5, as scipy.ndimage / skimage
_WIN = 2 * _RADIUS + 1  # 11


def _compute_dtype(device: torch.device) -> torch.dtype:
    return torch.float32 if device.type == "mps" else torch.float64


@contextlib.contextmanager
def _no_autocast(device: torch.device) -> Iterator[None]:
    try:
        ctx = torch.autocast(device_type=device.type, enabled=False)
    except (RuntimeError, ValueError):
        ctx = contextlib.nullcontext()
    with ctx:
        yield


def _validate(fn: str, pred: object, target: object, *, image: bool) -> tuple[Tensor, Tensor]:
    """Common checks; returns (pred, target) in the compute dtype, as [N, ...] (image: [N, C, H, W])."""
    for name, x in (("pred", pred), ("target", target)):
        if not isinstance(x, Tensor):
            raise TypeError(f"{fn}: {name} must be a torch.Tensor, got {type(x).__name__}")
        if not x.is_floating_point():
            raise TypeError(f"{fn}: {name} must be a floating-point tensor, got dtype {x.dtype}")
    assert isinstance(pred, Tensor) and isinstance(target, Tensor)
    if pred.shape != target.shape:
        raise ValueError(
            f"{fn}: pred and target must have the same shape, got pred {tuple(pred.shape)} "
            f"and target {tuple(target.shape)}"
        )
    if pred.device != target.device:
        raise ValueError(f"{fn}: pred is on {pred.device} but target is on {target.device}")
    if image:
        if pred.ndim not in (3, 4):
            raise ValueError(
                f"{fn}: expected [N, H, W] or [N, C, H, W] images, got pred/target of shape {tuple(pred.shape)}"
            )
        h, w = pred.shape[-2:]
        if h < _WIN or w < _WIN:
            raise ValueError(f"{fn}: images are {h}x{w}; the {_WIN}x{_WIN} Gaussian window needs H, W >= {_WIN}")
    elif pred.ndim < 1:
        raise ValueError(f"{fn}: expected a batch [N, ...], got a 0-d tensor")
    dtype = _compute_dtype(pred.device)
    p = pred.detach().to(dtype)
    t = target.detach().to(dtype)
    for name, x in (("pred", p), ("target", t)):
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"{fn}: {name} contains non-finite values (NaN or Inf); shape {tuple(x.shape)}")
    return p, t


def mse_per_sample(pred: Tensor, target: Tensor) -> Tensor:
    """Mean squared error per sample: ``mean((pred - target)**2)`` over all but dim 0 -> [N] float32."""
    with torch.no_grad(), _no_autocast(pred.device if isinstance(pred, Tensor) else torch.device("cpu")):
        p, t = _validate("mse_per_sample", pred, target, image=False)
        if p.numel() == 0:
            return torch.zeros(p.shape[0], dtype=torch.float32, device=p.device)
        return (p - t).square().reshape(p.shape[0], -1).mean(dim=1).to(torch.float32)


def psnr_per_sample(pred: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """PSNR per sample in dB: ``10 * log10(data_range**2 / max(mse, 1e-10))`` -> [N] float32.

    The MSE is clamped below at ``MSE_FLOOR = 1e-10``, so identical images give a finite
    cap of ``10 * log10(data_range**2 / 1e-10)`` = **100 dB for data_range = 1** (not inf),
    which keeps means over a test set finite. Otherwise matches
    ``skimage.metrics.peak_signal_noise_ratio(target, pred, data_range=data_range)``.
    """
    if not (isinstance(data_range, (int, float)) and math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"psnr_per_sample: data_range must be a positive finite number, got {data_range!r}")
    with torch.no_grad(), _no_autocast(pred.device if isinstance(pred, Tensor) else torch.device("cpu")):
        p, t = _validate("psnr_per_sample", pred, target, image=False)
        if p.numel() == 0:
            return torch.zeros(p.shape[0], dtype=torch.float32, device=p.device)
        mse = (p - t).square().reshape(p.shape[0], -1).mean(dim=1).clamp_min(MSE_FLOOR)
        return (10.0 * torch.log10(float(data_range) ** 2 / mse)).to(torch.float32)


def _gauss1d(dtype: torch.dtype) -> Tensor:
    x = torch.arange(-_RADIUS, _RADIUS + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / _SIGMA) ** 2)  # scipy.ndimage._gaussian_kernel1d
    return (g / g.sum()).to(dtype)


@functools.lru_cache(maxsize=8)
def _valid_filter_matrices(h: int, w: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """Banded matrices so that ``gh @ img @ gw`` is the valid 11x11 separable Gaussian filter.

    ``gh``: [H-10, H], ``gw``: [W, W-10]. A (batched) matmul is several times faster on
    CPU than a grouped float64 conv2d with 1-D kernels; same sum up to rounding (~1e-16).
    """
    g = _gauss1d(dtype)
    gh = torch.zeros(h - 2 * _RADIUS, h, dtype=dtype)
    gw = torch.zeros(w, w - 2 * _RADIUS, dtype=dtype)
    ih = torch.arange(h - 2 * _RADIUS)
    iw = torch.arange(w - 2 * _RADIUS)
    for k in range(_WIN):
        gh[ih, ih + k] = g[k]
        gw[iw + k, iw] = g[k]
    return gh.to(device), gw.to(device)


def ssim_per_sample(pred: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Mean SSIM per sample -> [N] float32, scikit-image's Gaussian convention.

    Equals ``skimage.metrics.structural_similarity(pred[i], target[i], data_range=data_range,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``: K1 = 0.01, K2 = 0.03,
    normalized 11x11 Gaussian window (sigma 1.5, radius 5), population covariances, SSIM map
    averaged over the *valid* region (skimage filters then crops 5 px at each border; a valid
    separable convolution is the same thing). Computed in float64: agreement with skimage
    is at the float32 rounding of the result (~1e-8).

    Accepts [N, H, W] or [N, C, H, W] (H, W >= 11); with C > 1 the per-channel means are
    averaged (skimage's ``channel_axis`` behaviour). Any float dtype; computed in float64.
    """
    if not (isinstance(data_range, (int, float)) and math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"ssim_per_sample: data_range must be a positive finite number, got {data_range!r}")
    with torch.no_grad(), _no_autocast(pred.device if isinstance(pred, Tensor) else torch.device("cpu")):
        p, t = _validate("ssim_per_sample", pred, target, image=True)
        n = p.shape[0]
        if p.ndim == 3:
            p, t = p.unsqueeze(1), t.unsqueeze(1)
        c, h, w = p.shape[1:]
        if p.numel() == 0:
            return torch.zeros(n, dtype=torch.float32, device=p.device)
        x = p.reshape(n * c, 1, h, w)
        y = t.reshape(n * c, 1, h, w)
        stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5, H, W]
        gh, gw = _valid_filter_matrices(h, w, p.dtype, p.device)
        f = gh @ (stack @ gw)  # valid separable Gaussian filter: [B, 5, H-10, W-10]
        ux, uy, uxx, uyy, uxy = f.unbind(dim=1)
        c1 = (_K1 * data_range) ** 2
        c2 = (_K2 * data_range) ** 2
        uxuy = ux * uy
        ux2 = ux * ux
        uy2 = uy * uy
        # skimage: A1 = 2 ux uy + C1, A2 = 2 vxy + C2, B1 = ux^2 + uy^2 + C1, B2 = vx + vy + C2,
        # with vx = uxx - ux^2, vy = uyy - uy^2, vxy = uxy - ux uy; S = A1 A2 / (B1 B2).
        a1 = uxuy.mul(2).add_(c1)
        a2 = (uxy - uxuy).mul_(2).add_(c2)
        b1 = (ux2 + uy2).add_(c1)
        b2 = (uxx - ux2).add_(uyy).sub_(uy2).add_(c2)
        s = a1.mul_(a2).div_(b1.mul_(b2))
        return s.mean(dim=(1, 2)).view(n, c).mean(dim=1).to(torch.float32)
