"""Plain-torch LPIPS v0.1 (AlexNet, linearly calibrated), no torchvision.

Weights: :mod:`graf.metrics.lpips_weights` (pretrained, offline, sha256-pinned).
Reference: Zhang et al., "The Unreasonable Effectiveness of Deep Features as a
Perceptual Metric", CVPR 2018 (github.com/richzhang/PerceptualSimilarity).
"""

from __future__ import annotations

import contextlib
import copy
import functools
import os
from collections.abc import Iterator
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

# graf.metrics.lpips_weights is imported inside functions: `python -m graf.metrics.lpips_weights`
# then does not find it pre-imported by the package (runpy's double-import warning).

__all__ = ["AlexNetTrunk", "LPIPS", "load_lpips", "lpips_distance", "get_lpips_model", "clear_lpips_cache"]

_TAP_CHANNELS = (64, 192, 384, 256, 256)
#: smallest H/W AlexNet's two 3x3/2 max-pools accept (conv1 k11 s4 p2 -> >=7 -> pool -> >=3 -> pool).
MIN_SIDE = 31
#: tolerance of the [0, 1] range check in :func:`lpips_distance`.
RANGE_TOLERANCE = 0.05


class AlexNetTrunk(nn.Module):
    """AlexNet ``features`` (torchvision layout); returns the 5 post-ReLU activations."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2)
        self.conv2 = nn.Conv2d(64, 192, kernel_size=5, padding=2)
        self.conv3 = nn.Conv2d(192, 384, kernel_size=3, padding=1)
        self.conv4 = nn.Conv2d(384, 256, kernel_size=3, padding=1)
        self.conv5 = nn.Conv2d(256, 256, kernel_size=3, padding=1)
        self.pool = nn.MaxPool2d(kernel_size=3, stride=2)

    def forward(self, x: Tensor) -> list[Tensor]:
        r1 = F.relu(self.conv1(x))
        r2 = F.relu(self.conv2(self.pool(r1)))
        r3 = F.relu(self.conv3(self.pool(r2)))
        r4 = F.relu(self.conv4(r3))
        r5 = F.relu(self.conv5(r4))
        return [r1, r2, r3, r4, r5]


def _unit_normalize(x: Tensor, eps: float = 1e-10) -> Tensor:
    return x / (torch.sqrt(torch.sum(x * x, dim=1, keepdim=True)) + eps)


class LPIPS(nn.Module):
    """LPIPS v0.1 distance. ``forward(in0, in1)`` takes [N, 3, H, W] RGB in [-1, 1], returns [N]."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.net = AlexNetTrunk()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in _TAP_CHANNELS)

    def forward(self, in0: Tensor, in1: Tensor) -> Tensor:
        n = in0.shape[0]
        x = (torch.cat([in0, in1], dim=0) - self.shift) / self.scale  # one pass for both
        total = None
        for feat, lin in zip(self.net(x), self.lins):
            f0, f1 = feat[:n], feat[n:]
            diff = (_unit_normalize(f0) - _unit_normalize(f1)) ** 2
            d = lin(diff).mean(dim=(2, 3)).squeeze(1)  # [N]
            total = d if total is None else total + d
        assert total is not None
        return total

    @torch.no_grad()
    def load_checkpoint_dict(self, ckpt: dict) -> LPIPS:
        """Load the nested numpy dict of ``alexnet.ckpt`` (flax HWIO kernels -> torch OIHW)."""

        def t(a) -> Tensor:  # noqa: ANN001
            return torch.from_numpy(a.copy()).float()

        state: dict[str, Tensor] = {"shift": self.shift.detach().clone(), "scale": self.scale.detach().clone()}
        alex = ckpt["AlexNet_0"]
        for i in range(5):
            conv = alex[f"Conv_{i}"]
            state[f"net.conv{i + 1}.weight"] = t(conv["kernel"].transpose(3, 2, 0, 1))
            state[f"net.conv{i + 1}.bias"] = t(conv["bias"])
            state[f"lins.{i}.weight"] = t(ckpt[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1))
        self.load_state_dict(state, strict=True)
        return self


def load_lpips(weights_path: str | os.PathLike[str] | None = None) -> LPIPS:
    """Build an :class:`LPIPS` with the pretrained weights (CPU, eval mode, no grad).

    ``weights_path=None`` resolves the file with :func:`find_weights`; raises
    ``LPIPSWeightsMissing`` / ``LPIPSWeightsInvalid`` -- never falls back to random weights.
    """
    # not at the top: setup.sh runs ``python -m graf.metrics.lpips_weights``, which imports this package first
    from .lpips_weights import load_checkpoint

    model = LPIPS().load_checkpoint_dict(load_checkpoint(weights_path))
    model.eval()
    model.requires_grad_(False)
    return model


# --------------------------------------------------------------------------- cached models


# The cached models are built outside inference mode even when first requested inside
# ``torch.inference_mode()`` (e.g. a Lightning test loop), so their parameters are ordinary tensors.


@functools.lru_cache(maxsize=2)
def _cpu_model(path: str) -> LPIPS:
    # fork_rng: building the network draws initial weights (then overwritten by the file's) from the global
    # generator; without it the first model made in a process got other weights than the next ones of the same
    # seed (a multirun's first job against its later ones)
    with torch.inference_mode(False), torch.random.fork_rng(devices=[]):
        return load_lpips(path)


@functools.lru_cache(maxsize=8)
def _device_model(path: str, device: torch.device) -> LPIPS:
    if device.type == "cpu":
        return _cpu_model(path)
    with torch.inference_mode(False):
        return copy.deepcopy(_cpu_model(path)).to(device)


def _resolve(weights_path: str | os.PathLike[str] | None) -> str:
    from .lpips_weights import find_weights  # not at the top: see load_lpips

    p = find_weights() if weights_path is None else Path(weights_path)
    return str(p.expanduser().resolve())


def get_lpips_model(device: torch.device | str = "cpu", weights_path: str | os.PathLike[str] | None = None) -> LPIPS:
    """The process-wide cached LPIPS model on ``device`` (loaded once per weight file and device)."""
    return _device_model(_resolve(weights_path), torch.device(device))


def clear_lpips_cache() -> None:
    """Forget cached models (e.g. after changing ``$GRAF_LPIPS_WEIGHTS``)."""
    _device_model.cache_clear()
    _cpu_model.cache_clear()


@contextlib.contextmanager
def _no_autocast(device: torch.device) -> Iterator[None]:
    """Disable autocast (e.g. Lightning ``*-mixed`` precision) so the metric runs in full precision."""
    try:
        ctx = torch.autocast(device_type=device.type, enabled=False)
    except (RuntimeError, ValueError):  # device type without autocast support
        ctx = contextlib.nullcontext()
    with ctx:
        yield


# --------------------------------------------------------------------------- public function


def _check_image(name: str, x: object) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"lpips_distance: {name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"lpips_distance: {name} must be a floating-point tensor in [0, 1], got dtype {x.dtype}")
    if x.ndim != 4 or x.shape[1] not in (1, 3):
        raise ValueError(f"lpips_distance: {name} must have shape [N, C, H, W] with C = 1 or 3, got {tuple(x.shape)}")
    if x.shape[2] < MIN_SIDE or x.shape[3] < MIN_SIDE:
        raise ValueError(f"lpips_distance: {name} is {x.shape[2]}x{x.shape[3]}; AlexNet-LPIPS needs H, W >= {MIN_SIDE}")
    return x


def lpips_distance(img0: Tensor, img1: Tensor, weights_path: str | os.PathLike[str] | None = None) -> Tensor:
    """LPIPS v0.1 (AlexNet) distance per sample; lower = more similar.

    Args:
        img0, img1: float tensors of shape [N, C, H, W], C = 1 (repeated to RGB) or 3,
            values in [0, 1] (mapped to [-1, 1] internally), H, W >= 31, same device.
            Values slightly outside [0, 1] (by at most 0.05) are passed through unchanged;
            anything further out raises ``ValueError`` (catches [0, 255] / [-1, 1] inputs).
        weights_path: the LPIPS weight file (None: :func:`graf.metrics.lpips_weights.find_weights`).

    Returns:
        float32 tensor [N] on the inputs' device. Computed without grad, with autocast
        disabled, using a pretrained model loaded once per process and device.

    Raises:
        ValueError: shape mismatch, wrong rank/channels, too small, non-finite or out-of-range values.
        LPIPSWeightsMissing / LPIPSWeightsInvalid: see :mod:`graf.metrics.lpips_weights`.
    """
    _check_image("img0", img0)
    _check_image("img1", img1)
    if img0.shape != img1.shape:
        raise ValueError(
            f"lpips_distance: img0 and img1 must have the same shape, got img0 {tuple(img0.shape)} "
            f"and img1 {tuple(img1.shape)}"
        )
    if img0.device != img1.device:
        raise ValueError(f"lpips_distance: img0 is on {img0.device} but img1 is on {img1.device}")
    device = img0.device
    with torch.no_grad(), _no_autocast(device):
        x0 = img0.detach().to(torch.float32)
        x1 = img1.detach().to(torch.float32)
        if x0.numel() == 0:
            return torch.zeros(x0.shape[0], dtype=torch.float32, device=device)
        for name, x in (("img0", x0), ("img1", x1)):
            if not bool(torch.isfinite(x).all()):
                raise ValueError(f"lpips_distance: {name} contains non-finite values (NaN or Inf)")
            lo, hi = float(x.min()), float(x.max())
            if lo < -RANGE_TOLERANCE or hi > 1.0 + RANGE_TOLERANCE:
                raise ValueError(
                    f"lpips_distance: {name} must be in [0, 1] (images in [0, 255] or [-1, 1] are not "
                    f"accepted), got values in [{lo:.4g}, {hi:.4g}]"
                )
        if x0.shape[1] == 1:
            x0 = x0.expand(-1, 3, -1, -1)
            x1 = x1.expand(-1, 3, -1, -1)
        model = get_lpips_model(device, weights_path)
        return model(x0 * 2.0 - 1.0, x1 * 2.0 - 1.0)
