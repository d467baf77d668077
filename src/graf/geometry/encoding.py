"""Positional encodings (NeRF style, supplement D; sinusoidal for distances) and coordinate frames.

:class:`PositionalEncoding` maps ``x [..., D]`` to ``[x, sin(2^k pi x), cos(2^k pi x)]_{k < F}``, i.e.
``D + 2 * D * F`` dims: 63 for 3-D coordinates and 84 for 4-D ones (3-D + scene index) with F = 10.

:func:`normalize_positions` maps world coordinates (m) into the scene's normalised frame: centred on the
middle of the scene's ``bounds`` box and divided by its largest half-extent (one scale for the three
axes, so the frame is a similarity of the world: distances and directions keep their meaning, and a
flat scene, e.g. every transmitter at one height, does not blow one axis up).  Everything inside the
box (the transmitters and the gateway) lands in ``[-1, 1]^3``; voxels along rays of length
``ray_length`` may leave the box by up to about the box's diagonal, i.e. ``|x| <~ 3``.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class PositionalEncoding(nn.Module):
    """``x [..., D] -> [..., D * (include_input + 2 * num_freqs)]`` with frequencies ``2^k * pi``.

    Computed in float32 at least (also under autocast: sin/cos of high frequencies need the mantissa).
    """

    def __init__(self, num_freqs: int = 10, include_input: bool = True):
        super().__init__()
        self.num_freqs, self.include_input = int(num_freqs), bool(include_input)
        self.register_buffer(
            "freqs", math.pi * 2.0 ** torch.arange(self.num_freqs, dtype=torch.float32), persistent=False
        )

    def out_dim(self, in_dim: int) -> int:
        return in_dim * (int(self.include_input) + 2 * self.num_freqs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not x.is_floating_point() or x.dtype in (torch.float16, torch.bfloat16):
            x = x.float()
        xf = (x.unsqueeze(-1) * self.freqs.to(x.dtype)).flatten(-2)  # [..., D * F], per coordinate then freq
        parts = ([x] if self.include_input else []) + [torch.sin(xf), torch.cos(xf)]
        return torch.cat(parts, dim=-1)


def scene_frame(bounds: torch.Tensor, eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """``(centre [B, 3], scale [B])`` of the scene boxes ``bounds [B, 2, 3]`` (min, max)."""
    lo, hi = bounds[..., 0, :], bounds[..., 1, :]
    centre = 0.5 * (lo + hi)
    scale = (0.5 * (hi - lo)).amax(dim=-1).clamp_min(eps)
    return centre, scale


def normalize_positions(p: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """World positions ``p [B, ..., 3]`` -> the normalised frame of each batch item's scene box
    ``bounds [B, 2, 3]``: ``(p - centre) / max half-extent`` (``[-1, 1]^3`` inside the box)."""
    centre, scale = scene_frame(bounds.to(p.dtype))
    shape = (p.shape[0],) + (1,) * (p.dim() - 2)
    return (p - centre.view(*shape, 3)) / scale.view(*shape, 1)


def normalize_offsets(v: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """Displacements ``v [B, ..., 3]`` (e.g. neighbor - target) in the same frame (scaled, not centred)."""
    _, scale = scene_frame(bounds.to(v.dtype))
    return v / scale.view((v.shape[0],) + (1,) * (v.dim() - 1))


def to_gateway_frame(p: torch.Tensor, gw_pos: torch.Tensor, gw_rot: torch.Tensor) -> torch.Tensor:
    """World positions ``p [B, ..., 3]`` (m) -> metres in each item's gateway frame: origin at the array
    centre, axes those of the array (``gw_rot [B, 3, 3]`` is local -> world, so this is ``R^T (p - g)``).
    The frame every scene shares: the spectrum itself is measured in it."""
    shape = (p.shape[0],) + (1,) * (p.dim() - 2)
    v = p - gw_pos.to(p.dtype).view(*shape, 3)
    return torch.einsum("bij,b...i->b...j", gw_rot.to(p.dtype), v)


def to_gateway_axes(v: torch.Tensor, gw_rot: torch.Tensor) -> torch.Tensor:
    """Displacements ``v [B, ..., 3]`` (m, e.g. neighbor - target) in the gateway's axes (rotated, not moved)."""
    return torch.einsum("bij,b...i->b...j", gw_rot.to(v.dtype), v)


def sinusoidal_encoding(x: torch.Tensor, dim: int, max_period: float = 10_000.0) -> torch.Tensor:
    """Transformer-style encoding of a scalar ``x [...]`` (e.g. a distance in wavelengths) -> ``[..., dim]``:
    ``sin(x w_i), cos(x w_i)`` with ``w_i = max_period^(-i / (dim / 2))``, periods from 2 pi to
    ``2 pi max_period``.  Continuous in ``x``: defined for any distance, in any scene, at any sample count."""
    if dim < 2 or dim % 2:
        raise ValueError(f"sinusoidal_encoding needs an even dim >= 2, got {dim}")
    half = dim // 2
    w = torch.exp(-math.log(max_period) * torch.arange(half, device=x.device, dtype=torch.float32) / half)
    a = x.float().unsqueeze(-1) * w
    return torch.cat([torch.sin(a), torch.cos(a)], dim=-1)
