"""The receiving 4x4 array and its Bartlett spatial spectrum (facts: NeRF2 ``gen_spectrum.py``).

Gateway frame: the array lies in the plane z = 0 and faces +z.  Spectrum row r is elevation r+1 deg,
column c azimuth c+1 deg; the direction is d(a, e) = (cos e cos a, cos e sin a, sin e), so the 90 rows
cover the array's **front** hemisphere (z > 0) and elevation 90 deg is broadside.  The world direction
is R @ d with R the gateway rotation (quaternion x, y, z, w), as in NeRF2's ray grid.

With per-path complex gains g_p and arrival directions u_p (unit vectors from the array towards where
each path arrives from, gateway frame), antenna k at r_k receives

    h_k = sum_p g_p A(u_p) exp(+j 2 pi / lambda  r_k . u_p)

and the Bartlett beamformer gives P(a, e) = | sum_k exp(-j 2 pi / lambda  r_k . d(a, e)) h_k | / K,
min-max normalised over the grid (amplitude, not power).  A planar array cannot tell u from its mirror
image in the array plane: the element pattern A decides what arrives from behind.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from graf.geometry.grid import N_AZIMUTH, N_ELEVATION, grid_directions

PATTERNS = ("iso", "front", "cos")


def array_positions(wavelength: float, rows: int = 4, cols: int = 4, pitch_wavelengths: float = 0.5) -> np.ndarray:
    """Element positions ``[rows * cols, 3]`` (m) in the gateway frame, centred, in the plane z = 0.

    With 4 x 4 and a 0.16 m pitch this is NeRF2's x, y in {-0.24, -0.08, 0.08, 0.24}."""
    pitch = pitch_wavelengths * wavelength
    xs = (np.arange(cols) - (cols - 1) / 2) * pitch
    ys = (np.arange(rows) - (rows - 1) / 2) * pitch
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    return np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1)


def rotation_from_axes(normal, x_axis) -> Rotation:
    """Gateway rotation whose local +z is ``normal`` (the array faces it) and local +x (azimuth 0) is
    ``x_axis`` made orthogonal to it."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    x = np.asarray(x_axis, float)
    x = x - n * (x @ n)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"gateway x_axis {x_axis} is parallel to its normal {normal}")
    x = x / np.linalg.norm(x)
    return Rotation.from_matrix(np.stack([x, np.cross(n, x), n], axis=1))


def pattern_gain(u_local: torch.Tensor, pattern: str) -> torch.Tensor:
    """Element amplitude pattern for arrival directions ``[..., 3]`` in the gateway frame.

    iso: 1 everywhere (paths from behind fold onto their mirror direction); front: 1 in front, 0 behind
    (an ideal reflector behind the array); cos: cos of the angle to broadside in front, 0 behind (a patch)."""
    z = u_local[..., 2]
    if pattern == "iso":
        return torch.ones_like(z)
    if pattern == "front":
        return (z > 0).to(z.dtype)
    if pattern == "cos":
        return z.clamp_min(0.0)
    raise ValueError(f"unknown antenna pattern {pattern!r}; choose one of {PATTERNS}")


class Bartlett:
    """Channels ``[n, K]`` -> spectra ``[n, 90, 360]`` in [0, 1]; the steering matrix is built once."""

    def __init__(self, antenna_pos: np.ndarray, wavelength: float, device: str | torch.device = "cpu"):
        self.k = 2 * math.pi / wavelength
        self.pos = torch.as_tensor(antenna_pos, dtype=torch.float64, device=device)  # [K, 3]
        d = grid_directions().to(device)
        self.steer = torch.exp(-1j * self.k * (d @ self.pos.T)).to(torch.complex64)  # [G, K]
        self.device = torch.device(device)

    def channels(self, gains: torch.Tensor, u_local: torch.Tensor, pattern: str = "cos") -> torch.Tensor:
        """Per-antenna channels ``[n, K]`` from path gains ``[n, P]`` (complex, 0 for invalid paths) and
        arrival directions ``[n, P, 3]`` in the gateway frame."""
        g = gains.to(torch.complex128) * pattern_gain(u_local, pattern).to(torch.float64)
        phase = torch.exp(
            1j * self.k * torch.einsum("npc,kc->npk", u_local.to(torch.float64), self.pos.to(u_local.device))
        )
        return torch.einsum("np,npk->nk", g, phase).to(torch.complex64)

    def amplitude(self, h: torch.Tensor) -> torch.Tensor:
        """Unnormalised Bartlett amplitude ``[n, 90, 360]``."""
        h = h.to(device=self.device, dtype=torch.complex64)
        return (torch.abs(h @ self.steer.T) / self.pos.shape[0]).reshape(-1, N_ELEVATION, N_AZIMUTH)

    def spectra(self, h: torch.Tensor) -> torch.Tensor:
        """Min-max normalised spectra ``[n, 90, 360]`` (a channel with no paths gives all zeros)."""
        p = self.amplitude(h)
        lo = p.amin(dim=(1, 2), keepdim=True)
        span = p.amax(dim=(1, 2), keepdim=True) - lo
        return torch.where(span > 0, (p - lo) / span.clamp_min(1e-30), torch.zeros_like(p))


def to_uint8(spectra: torch.Tensor) -> np.ndarray:
    """Quantise like NeRF2's PNGs: pixel = round(255 * value)."""
    return torch.round(spectra.clamp(0, 1) * 255).to(torch.uint8).cpu().numpy()
