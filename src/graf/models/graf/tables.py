"""The voxels of every ray of a scene's spectrum (geometry only, no weights): where each ray enters the scene
box, its voxel length and count, and how many voxels it would need without the ``max_samples`` cap."""

from __future__ import annotations

from collections.abc import Callable

import torch

from graf.geometry.grid import local_directions
from graf.geometry.rays import box_segments, segment_samples

SCENE_TABLE_CHUNK = 65_536  # voxels per piece while building a scene's table


def scene_ray_table(geo: tuple, wl: float, spacing: float, max_samples: int, device) -> dict:
    """``geo``: the gateway's position ``[3]``, rotation ``[3, 3]`` and the scene box ``[2, 3]``; voxels of
        ``spacing`` wavelengths ``wl`` (metres), at most ``max_samples`` per ray.  ``t_in [P]`` (m, where the ray
        enters the box), ``step [P]`` (m, the voxel length), ``samples [P]`` (long), the pixel order by sample
        count (``order [P]``), each ray's first voxel in a flat table whose rays lie in that order (``offsets [P]``: the
    consecutive rays of a chunk of ``order`` with the same count are one slice of it), the voxels of all rays
        (``voxels``), the most on any ray (``most``) and those each ray needs uncapped (``needed [P]``, on the CPU)."""
    t_in, t_out = box_segments(*(g.detach().cpu() for g in geo), local_directions(dtype=torch.float64))
    samples, step = segment_samples(t_in, t_out, spacing * wl, max_samples)
    order = torch.argsort(samples, stable=True)
    offsets = torch.empty_like(samples)
    offsets[order] = torch.cumsum(samples[order], 0) - samples[order]  # rays in ``order``: a chunk is one slice
    needed = torch.ceil((t_out - t_in) / (spacing * wl) - 1e-6).clamp_min(1).long()
    return {
        "t_in": t_in.float().to(device),
        "step": step.float().to(device),
        "samples": samples.to(device),
        "order": order.to(device),
        "needed": needed,
        "offsets": offsets.to(device),
        "voxels": int(samples.sum()),
        "most": int(samples.max()),  # the longest ray's voxels: the static path's padded length (a Python int)
    }


def ray_sampling_summary(table: dict, wl: float, spacing: float) -> dict:
    """Voxels per ray of one scene's table: their most, mean and total, the voxel length, and whether the
    cap made any ray's voxels longer than ``spacing`` wavelengths."""
    capped = table["needed"] > table["samples"].cpu()
    return {
        "samples_per_ray": int(table["samples"].max()),
        "mean_samples_per_ray": float(table["samples"].float().mean()),
        "voxels_per_spectrum": table["voxels"],
        "sample_spacing_m": float(table["step"].max()),
        "sample_spacing_wavelengths": float(table["step"].max()) / wl,
        "nominal_spacing_wavelengths": spacing,
        "capped": bool(capped.any()),
        "capped_rays": int(capped.sum()),
        "uncapped_samples": int(table["needed"].max()),
        "sampling": "ray-box: each ray from its entry to its exit of the scene box",
    }


def flat_scene_voxels(
    table: dict, voxel_inputs: Callable, wl: float, scene_index: int, d_model: int, device
) -> tuple[torch.Tensor, torch.Tensor]:
    """``voxel_inputs`` (GRaF's ``(query, distance code)`` of rays' voxels) of every voxel of a scene's spectrum,
    flat ``[V, d_model]`` each (rays in ``table["order"]``, each ray's first voxel at ``table["offsets"]``), computed in
    pieces of about :data:`SCENE_TABLE_CHUNK` voxels."""
    qs, cs = [], []
    for S in torch.unique(table["samples"]).tolist():
        sel = (table["samples"] == S).nonzero().flatten()
        for part in sel.split(max(1, SCENE_TABLE_CHUNK // S)):
            n = part.numel()
            q, c = voxel_inputs(
                part,
                table["t_in"][part],
                table["step"][part],
                torch.full((n,), wl, device=device),
                torch.full((n,), scene_index, device=device, dtype=torch.long),
                S,
            )
            qs.append((part, q)), cs.append(c)
    qf = torch.empty(table["voxels"], d_model, device=device, dtype=qs[0][1].dtype)
    cf = torch.empty(table["voxels"], d_model, device=device, dtype=cs[0].dtype)
    for (part, q), c in zip(qs, cs):
        idx = (table["offsets"][part][:, None] + torch.arange(q.shape[1], device=device)).flatten()
        qf[idx], cf[idx] = q.flatten(0, 1), c.flatten(0, 1)
    return qf, cf


def geometry_key(gw_pos: torch.Tensor, gw_rot: torch.Tensor, bounds: torch.Tensor, wl) -> tuple:
    """A scene table's key: the geometry's own values (not a scene number) and the wavelength, as Python floats.
    Read from the batch on the host (:meth:`GRaFModule.on_before_batch_transfer`), a step on a GPU needs no copy
    back to find its tables."""
    geo = torch.cat([g.detach().double().flatten().cpu() for g in (gw_pos, gw_rot, bounds)])
    return (*geo.tolist(), float(wl))
