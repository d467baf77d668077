"""The spatial-spectrum grid, defined once for the whole package.

A spectrum is ``[90, 360]``: row r (0-based) is elevation r + 1 deg, column c azimuth c + 1 deg (NeRF2's
model grid).  Pixel ``p = r * 360 + c`` is the ray leaving the gateway in the local direction
``(cos e cos a, cos e sin a, sin e)``; the world direction is ``gw_rot @ d``.
"""

from __future__ import annotations

import torch

N_ELEVATION, N_AZIMUTH = 90, 360
SPECTRUM_SHAPE = (N_ELEVATION, N_AZIMUTH)
N_RAYS = N_ELEVATION * N_AZIMUTH


def directions(el_deg: torch.Tensor, az_deg: torch.Tensor) -> torch.Tensor:
    """Unit directions ``[len(el) * len(az), 3]`` (gateway frame, azimuth fastest) of every (elevation,
    azimuth) pair in degrees: ``(cos e cos a, cos e sin a, sin e)``."""
    e, a = torch.meshgrid(torch.deg2rad(el_deg), torch.deg2rad(az_deg), indexing="ij")
    return torch.stack([torch.cos(e) * torch.cos(a), torch.cos(e) * torch.sin(a), torch.sin(e)], -1).reshape(-1, 3)


def grid_directions(dtype=torch.float64) -> torch.Tensor:
    """Unit directions ``[90 * 360, 3]`` of the spectrum grid in the gateway frame (azimuth fastest)."""
    return directions(torch.arange(1, N_ELEVATION + 1, dtype=dtype), torch.arange(1, N_AZIMUTH + 1, dtype=dtype))


def local_directions(device=None, dtype=torch.float32) -> torch.Tensor:
    """``[32400, 3]`` unit ray directions in the gateway frame (row-major: ``r * 360 + c``)."""
    return grid_directions(torch.float64).to(device=device, dtype=dtype)
