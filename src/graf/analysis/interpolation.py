"""The interpolation theorem measured (supplement A.1): the error of a convex combination of neighbors'
spectra against the largest neighbor distance dP, and the local curvature constant K that bounds it
(``error <= K dP**2`` where the field is smooth).

- :func:`interpolation_errors`: every target of a set interpolated from its L nearest other positions with
  barycentric or IDW weights; per target the largest neighbor distance and the mean squared error.
- :func:`curvature`: K at a position from a field ``trace(positions) -> spectra`` (the simulator), by central
  second differences along the three axes: the root mean square over pixels of the largest second directional
  derivative (per metre squared).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from graf.data.neighbors import select_neighbors
from graf.models.knn.weights import barycentric_weights, idw_weights

WEIGHTINGS = ("barycentric", "idw")


def interpolation_errors(
    positions, spectra, L: int, weighting: str = "barycentric", targets=None, chunk: int = 256
) -> dict[str, np.ndarray]:
    """Interpolate each target's spectrum from its ``L`` nearest other positions of the set.

    ``positions`` ``[N, 3]`` (m), ``spectra`` ``[N, 90, 360]`` (or ``[N, P]``); ``targets``: the rows to
    interpolate (default: all).  Returns ``{"target", "dp_max", "dp_mean", "mse", "rmse"}``, one entry per
    target: the largest and mean neighbor distance (m) and the (root) mean squared error of the interpolated
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


# the 8 corners of a cube: a target at their centre lies inside their convex hull, so barycentric weights exist
_CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) / np.sqrt(3.0)


def cluster_errors(trace: Callable[[np.ndarray], np.ndarray], anchors, scales, seed: int = 0) -> dict[str, np.ndarray]:
    """Interpolation error at fine scales, from a field ``trace`` (the simulator): around every anchor and for
    every scale ``d`` (m), eight neighbors towards the corners of a randomly rotated cube (each direction jittered,
    one per octant) at distances drawn in [d/2, d] (the largest set to d, so ``dp_max == d``); the anchor is
    interpolated from them with barycentric and IDW weights.  Returns ``{"anchor", "scale", "dp_max",
    "rmse_barycentric", "rmse_idw"}`` (one entry per anchor and scale), all traced in one call per scale."""
    anchors = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("anchor", "scale", "dp_max", "rmse_barycentric", "rmse_idw")}
    for d in np.asarray(scales, dtype=np.float64):
        if not d > 0:
            raise ValueError(f"scales must be > 0 m, got {d}")
        rot = Rotation.random(len(anchors), random_state=rng).as_matrix()  # [A, 3, 3]
        # the corners jittered (one per octant still, so the anchor stays inside the hull), so that the directions
        # do not sum to zero: on an exactly symmetric set IDW would reproduce a linear field by accident
        dirs = _CUBE[None] + 0.2 * rng.standard_normal((len(anchors), 8, 3))
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        radius = rng.uniform(0.5, 1.0, size=(len(anchors), 8)) * d
        radius[np.arange(len(anchors)), rng.integers(0, 8, len(anchors))] = d
        offsets = np.einsum("aij,akj->aki", rot, dirs) * radius[..., None]  # [A, 8, 3]
        nbr = anchors[:, None, :] + offsets
        pts = np.concatenate([anchors[:, None, :], nbr], axis=1).reshape(-1, 3)
        s = np.asarray(trace(pts), dtype=np.float64).reshape(len(anchors), 9, -1)
        tgt, nb_s = torch.from_numpy(anchors), torch.from_numpy(nbr)
        mask = torch.ones(len(anchors), 8, dtype=torch.bool)
        for name, fn in (("barycentric", barycentric_weights), ("idw", idw_weights)):
            w = fn(tgt, nb_s, mask).double().numpy()
            pred = np.einsum("al,alp->ap", w, s[:, 1:])
            out[f"rmse_{name}"].append(np.sqrt(np.mean((pred - s[:, 0]) ** 2, axis=1)))
        out["anchor"].append(np.arange(len(anchors)))
        out["scale"].append(np.full(len(anchors), d))
        out["dp_max"].append(np.linalg.norm(offsets, axis=-1).max(axis=1))
    return {k: np.concatenate(v) for k, v in out.items()}


def local_slopes(scale, error) -> tuple[np.ndarray, np.ndarray]:
    """The log-log slope of the median error between consecutive scales: ``(midpoints, slopes)``; a slope near 2
    is the theorem's quadratic regime, near 0 a field decorrelated at that distance."""
    scale, error = np.asarray(scale, dtype=np.float64), np.asarray(error, dtype=np.float64)
    s = np.unique(scale)
    med = np.array([np.median(error[scale == v]) for v in s])
    if len(s) < 2:
        return np.array([]), np.array([])
    slopes = np.diff(np.log10(np.maximum(med, 1e-300))) / np.diff(np.log10(s))
    return np.sqrt(s[1:] * s[:-1]), slopes


def quadratic_up_to(scale, error, threshold: float = 1.5) -> float | None:
    """The largest scale (m) up to which every local slope from the finest scale on stays >= ``threshold``: where
    the quadratic law holds (None when it does not hold even between the two finest scales)."""
    mids, slopes = local_slopes(scale, error)
    s = np.unique(np.asarray(scale, dtype=np.float64))
    last = None
    for i, sl in enumerate(slopes):
        if sl < threshold:
            break
        last = float(s[i + 1])
    return last


def curvature_map(trace: Callable[[np.ndarray], np.ndarray], points, h: float, chunk: int = 128) -> np.ndarray:
    """:func:`curvature` at every point ``[M, 3]``, the stencils of ``chunk`` points traced per call (memory
    bounded: an outdoor floor grid of 8,000 points in one call, 56,000 spectra, once took all 24 GB)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    stencil = np.concatenate([np.zeros((1, 3))] + [s * h * e[None] for e in np.eye(3) for s in (1.0, -1.0)])
    out = []
    for i in range(0, len(pts), max(1, int(chunk))):
        part = pts[i : i + max(1, int(chunk))]
        batch = (part[:, None, :] + stencil[None]).reshape(-1, 3)
        spectra = np.asarray(trace(batch), dtype=np.float64).reshape(len(part), 7, -1)
        out += [curvature(lambda _p, s=s: s, p, h) for p, s in zip(part, spectra)]
    return np.array(out, dtype=np.float64).reshape(len(pts))
