"""Angle of arrival from a spatial spectrum, and the geometric truth to score it against (seed's AoA case study).

A spectrum is ``[90, 360]`` in the angle convention of :mod:`graf.geometry.grid`: row r is elevation r + 1 deg,
column c azimuth c + 1 deg, the direction ``(cos e cos a, cos e sin a, sin e)`` in the gateway frame.

- :func:`peak_direction`: the strongest pixel, refined to a fraction of a degree by a quadratic through it and its
  two neighbors along each axis (azimuth wraps at 360 deg; at elevation 1 or 90 deg the edge is kept).
- :func:`arrival_direction`: the direction a transmitter is seen from by the gateway (the direct path's angle of
  arrival), as (elevation, azimuth) in the same convention; a transmitter behind the array plane is mirrored into
  the front hemisphere, which is all a planar array can tell (:mod:`graf.sim.array`).
- :func:`angular_error`: the great-circle angle between two directions, in degrees.
"""

from __future__ import annotations

import numpy as np

from graf.geometry.grid import N_AZIMUTH, N_ELEVATION


def _vertex(left: float, mid: float, right: float) -> float:
    """Offset in (-0.5, 0.5) of the vertex of the parabola through three equally spaced samples (0 if flat)."""
    den = left - 2.0 * mid + right
    if den >= 0.0 or not np.isfinite(den):  # not a strict maximum: keep the pixel
        return 0.0
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


def peak_direction(spectrum) -> tuple[float, float]:
    """``(elevation, azimuth)`` in degrees of the strongest peak of a ``[90, 360]`` spectrum, refined between
    pixels; azimuth in [0.5, 360.5) wrapped to (0, 360]."""
    s = np.asarray(spectrum, dtype=np.float64)
    if s.shape != (N_ELEVATION, N_AZIMUTH):
        raise ValueError(f"a spectrum is [{N_ELEVATION}, {N_AZIMUTH}], got {list(s.shape)}")
    if not np.isfinite(s).all():
        raise ValueError("the spectrum holds NaN or infinite values")
    r, c = np.unravel_index(int(np.argmax(s)), s.shape)
    da = _vertex(s[r, (c - 1) % N_AZIMUTH], s[r, c], s[r, (c + 1) % N_AZIMUTH])
    de = _vertex(s[r - 1, c], s[r, c], s[r + 1, c]) if 0 < r < N_ELEVATION - 1 else 0.0
    az = (c + 1 + da) % 360.0
    return float(r + 1 + de), float(az if az > 0 else az + 360.0)


def direction_to_angles(u) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions ``[..., 3]`` in the gateway frame -> (elevation, azimuth) in degrees, azimuth in (0, 360].
    A direction behind the array (z < 0) is mirrored to the front (elevation >= 0)."""
    u = np.asarray(u, dtype=np.float64)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    el = np.degrees(np.arcsin(np.clip(np.abs(u[..., 2]), 0.0, 1.0)))
    az = np.degrees(np.arctan2(u[..., 1], u[..., 0])) % 360.0
    return el, np.where(az > 0, az, az + 360.0)


def angles_to_direction(el_deg, az_deg) -> np.ndarray:
    """(elevation, azimuth) in degrees -> unit directions ``[..., 3]`` in the gateway frame."""
    e, a = np.radians(np.asarray(el_deg, dtype=np.float64)), np.radians(np.asarray(az_deg, dtype=np.float64))
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)


def arrival_direction(tx_pos, gw_pos, gw_rot) -> tuple[np.ndarray, np.ndarray]:
    """The direct path's angle of arrival of transmitters ``[..., 3]`` (m, world) at a gateway at ``gw_pos``
    with rotation matrix ``gw_rot`` (local -> world), as (elevation, azimuth) in degrees."""
    d = np.asarray(tx_pos, dtype=np.float64) - np.asarray(gw_pos, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(n == 0):
        raise ValueError("a transmitter at the gateway's own position has no angle of arrival")
    local = (d / n) @ np.asarray(gw_rot, dtype=np.float64)  # R^T d for each row
    return direction_to_angles(local)


def angular_error(el1, az1, el2, az2) -> np.ndarray:
    """Great-circle angle in degrees between (el1, az1) and (el2, az2)."""
    u, v = angles_to_direction(el1, az1), angles_to_direction(el2, az2)
    return np.degrees(np.arccos(np.clip(np.sum(u * v, axis=-1), -1.0, 1.0)))
