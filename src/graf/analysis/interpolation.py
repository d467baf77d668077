"""The interpolation theorem measured (seed appendix A.1): the error of a convex combination of neighbours'
spectra against the largest neighbour distance dP, and the local curvature constant K that bounds it
(``error <= K dP**2`` where the field is smooth).

- :func:`interpolation_errors`: every target of a set interpolated from its L nearest other positions with
  barycentric or IDW weights; per target the largest neighbour distance and the mean squared error.
- :func:`curvature`: K at a position from a field ``trace(positions) -> spectra`` (the simulator), by central
  second differences along the three axes: the root mean square over pixels of the largest second directional
  derivative (per metre squared).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from graf.models.knn.weights import barycentric_weights, idw_weights
from graf.neighbors import select_neighbors

WEIGHTINGS = ("barycentric", "idw")


def interpolation_errors(
    positions, spectra, L: int, weighting: str = "barycentric", targets=None, chunk: int = 256
) -> dict[str, np.ndarray]:
    """Interpolate each target's spectrum from its ``L`` nearest other positions of the set.

    ``positions`` ``[N, 3]`` (m), ``spectra`` ``[N, 90, 360]`` (or ``[N, P]``); ``targets``: the rows to
    interpolate (default: all).  Returns ``{"target", "dp_max", "dp_mean", "mse", "rmse"}``, one entry per
    target: the largest and mean neighbour distance (m) and the (root) mean squared error of the interpolated
    spectrum.  The theorem bounds the error itself, so its slope against ``dp_max`` is read on ``rmse``."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting={weighting!r}: one of {', '.join(WEIGHTINGS)}")
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float64)
    spec = torch.as_tensor(np.asarray(spectra), dtype=torch.float64).reshape(pos.shape[0], -1)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be [N, 3], got {list(pos.shape)}")
    n = pos.shape[0]
    if n < 2:
        raise ValueError("interpolation needs at least two positions")
    rows = torch.arange(n) if targets is None else torch.as_tensor(np.asarray(targets), dtype=torch.long)
    ids = torch.arange(n)
    out = {k: [] for k in ("target", "dp_max", "dp_mean", "mse")}
    for start in range(0, len(rows), chunk):
        t = rows[start : start + chunk]
        nb = select_neighbors(pos[t], pos, min(L, n - 1), target_ids=ids[t], cand_ids=ids)
        nbr = pos[nb.index]
        w = (barycentric_weights if weighting == "barycentric" else idw_weights)(pos[t], nbr, nb.mask).double()
        pred = torch.einsum("tl,tlp->tp", w, spec[nb.index])
        d = torch.where(nb.mask, nb.distance.double(), torch.zeros_like(nb.distance.double()))
        out["target"].append(t.numpy())
        out["dp_max"].append(d.amax(dim=1).numpy())
        out["dp_mean"].append((d.sum(dim=1) / nb.mask.sum(dim=1)).numpy())
        out["mse"].append(((pred - spec[t]) ** 2).mean(dim=1).numpy())
    res = {k: np.concatenate(v) for k, v in out.items()}
    res["rmse"] = np.sqrt(res["mse"])
    return res


def curvature(trace: Callable[[np.ndarray], np.ndarray], position, h: float) -> float:
    """K at ``position`` (m): RMS over pixels of the largest |second derivative| along x, y, z, from central
    differences with step ``h`` (m) of ``trace`` (``[M, 3]`` positions -> ``[M, ...]`` spectra)."""
    if not h > 0:
        raise ValueError(f"the finite-difference step must be > 0 m, got {h}")
    p = np.asarray(position, dtype=np.float64).reshape(3)
    pts = [p] + [p + s * h * e for e in np.eye(3) for s in (1.0, -1.0)]
    s = np.asarray(trace(np.stack(pts)), dtype=np.float64).reshape(7, -1)
    second = np.stack([(s[1 + 2 * i] - 2.0 * s[0] + s[2 + 2 * i]) / h**2 for i in range(3)])  # [3, P]
    return float(np.sqrt(np.mean(np.abs(second).max(axis=0) ** 2)))
