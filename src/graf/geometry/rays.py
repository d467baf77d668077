"""Rays of the spectrum grid and the samples along them (supplement D, "Voxel Size").

Pixel ``p = r * 360 + c`` of a 90 x 360 spectrum is the ray leaving the gateway at elevation ``r + 1`` deg
and azimuth ``c + 1`` deg: local direction ``(cos e cos a, cos e sin a, sin e)``
(:func:`graf.geometry.grid.grid_directions`), world direction ``gw_rot @ d`` (:func:`world_directions`).

A ray of length ``ray_length`` (m) holds ``S = min(max_samples, ceil(ray_length / spacing))`` samples
(:func:`num_samples`, per batch item: scene and band come from the batch, nothing is global).  GRaF cuts each
ray's own stretch inside the scene box into voxels one wavelength long (:func:`box_segments`,
:func:`segment_samples`); NeRF2 samples from its near plane to the ray length.
"""

from __future__ import annotations

import math

import torch

from graf.geometry.grid import N_AZIMUTH, N_ELEVATION, N_RAYS


def num_samples(ray_length: torch.Tensor, wavelength: torch.Tensor, max_samples: int) -> list[int]:
    """Voxels per ray for each batch item: ``min(max_samples, ceil(ray_length / wavelength))`` (>= 1)."""
    ratio = (ray_length.detach().double() / wavelength.detach().double()).cpu().tolist()
    return [max(1, min(int(max_samples), math.ceil(x - 1e-6))) for x in ratio]


def world_directions(gw_rot: torch.Tensor, dirs_local: torch.Tensor) -> torch.Tensor:
    """``gw_rot [B, 3, 3]`` (local -> world) applied to ``dirs_local [B, R, 3]`` or ``[R, 3]`` -> ``[B, R, 3]``."""
    if dirs_local.dim() == 2:
        return torch.einsum("bij,rj->bri", gw_rot, dirs_local.to(gw_rot.dtype))
    return torch.einsum("bij,brj->bri", gw_rot, dirs_local.to(gw_rot.dtype))


def random_pixels(batch_size: int, rays_per_step: int, step: int, device=None) -> torch.Tensor:
    """``[B, R]`` random pixels for a training step, ``R = rays_per_step // B`` (at least 1, at most 32400) per
    target, without replacement per target; the generator is seeded from ``step`` (reproducible, resumable)."""
    R = min(N_RAYS, max(1, rays_per_step // batch_size))
    g = torch.Generator().manual_seed(int(step))
    return torch.rand(batch_size, N_RAYS, generator=g).argsort(dim=1)[:, :R].to(device)


def render_spectra(render, ctx: dict, batch_size: int, chunk_rays: int, device=None) -> torch.Tensor:
    """Whole ``[B, 90, 360]`` spectra from ``render(ctx, pix [B, R]) -> [B, R]``, in chunks of at most
    ``chunk_rays`` rays over the whole batch (memory bounded by the chunk, not by the spectrum)."""
    per = max(1, chunk_rays // batch_size)
    allpix = torch.arange(N_RAYS, device=device)
    out = [render(ctx, allpix[s : s + per].expand(batch_size, -1)) for s in range(0, N_RAYS, per)]
    return torch.cat(out, dim=1).view(batch_size, N_ELEVATION, N_AZIMUTH).float()


def fp32(device: torch.device):
    """Autocast off: ray geometry, positional-encoding phases and rendering stay fp32 under mixed precision."""
    return torch.autocast(device_type=device.type, enabled=False)


# ---------------------------------------------------------------------------------------------------------
# Ray-box sampling (GRaF): each ray's voxels from its own entry to its own exit of the scene box.


def box_segments(
    gw_pos: torch.Tensor, gw_rot: torch.Tensor, bounds: torch.Tensor, dirs_local: torch.Tensor, eps: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each ray from the gateway is inside the scene box (slab method, float64).

    ``gw_pos [3]``, ``gw_rot [3, 3]`` (local -> world), ``bounds [2, 3]`` (min, max), ``dirs_local [R, 3]``
    -> ``(t_in [R], t_out [R])`` in metres along the ray, ``0 <= t_in <= t_out``: the ray enters the box at
    ``t_in`` (0 when the gateway is inside it) and leaves it at ``t_out``.  A ray that misses the box, or
    leaves it at once (a gateway on a face, looking out), gets ``t_in = t_out`` (a segment of length 0).
    """
    p = gw_pos.double()
    w = dirs_local.double() @ gw_rot.double().T  # [R, 3] world directions
    lo, hi = bounds[0].double(), bounds[1].double()
    parallel = w.abs() < eps
    safe = torch.where(parallel, torch.ones_like(w), w)
    t1, t2 = (lo - p) / safe, (hi - p) / safe
    inside = (p >= lo) & (p <= hi)  # per axis: a ray parallel to a slab is in it for all t iff its origin is
    inf = torch.full_like(t1, float("inf"))
    near = torch.where(parallel, torch.where(inside, -inf, inf), torch.minimum(t1, t2)).amax(dim=1)
    far = torch.where(parallel, torch.where(inside, inf, -inf), torch.maximum(t1, t2)).amin(dim=1)
    t_in = near.clamp_min(0.0)
    hit = torch.isfinite(far) & (far > t_in)
    t_in = torch.where(hit, t_in, torch.zeros_like(t_in))
    t_out = torch.where(hit, far, t_in)
    return t_in, t_out


def segment_samples(
    t_in: torch.Tensor, t_out: torch.Tensor, voxel: float, max_samples: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxels of length ``voxel`` (m) over each segment: ``(samples [R] long, step [R])`` with
    ``samples = clamp(ceil((t_out - t_in) / voxel), 1, max_samples)`` and ``step = (t_out - t_in) / samples``
    (voxel centres at ``t_in + (s + 0.5) * step``; a length-0 segment is one voxel at ``t_in``)."""
    length = (t_out - t_in).double()
    s = torch.ceil(length / float(voxel) - 1e-6).clamp(1, int(max_samples)).long()
    return s, length / s
