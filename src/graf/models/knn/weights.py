"""Neighbor weights for linear spectrum interpolation (supplement A).

Both functions take the target positions ``[T, 3]``, the neighbors' positions ``[T, L, 3]`` and their
mask ``[T, L]`` and return weights ``[T, L]`` that are >= 0, zero where masked, and sum to 1.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import nnls


def idw_weights(
    target: torch.Tensor, nbr: torch.Tensor, mask: torch.Tensor, power: float = 1.0, eps: float = 1e-9
) -> torch.Tensor:
    """Inverse-distance weights w_i ~ 1 / d_i^power.

    Neighbors at distance < ``eps`` (co-located with the target) take all the weight, shared equally.
    """
    d = torch.linalg.vector_norm(nbr.double() - target.double().unsqueeze(1), dim=-1)  # [T, L]
    m = mask.bool()
    zero = (d < eps) & m
    w = torch.where(m, 1.0 / d.clamp_min(eps) ** power, torch.zeros_like(d))
    w = torch.where(zero.any(dim=1, keepdim=True), zero.double(), w)
    return (w / w.sum(dim=1, keepdim=True)).to(nbr.dtype)


def barycentric_weights(
    target: torch.Tensor, nbr: torch.Tensor, mask: torch.Tensor, ridge: float = 1e-3, sum_weight: float = 1e3
) -> torch.Tensor:
    """Barycentric weights of the interpolation theorem (supplement A.1, ASSUMPTION 2).

    Solves, per target, the non-negative least-squares problem

        min_w  || sum_i w_i (P_i - P_t) ||^2  +  ridge * sum_i (w_i d_i)^2,   w >= 0,  sum_i w_i = 1

    (lengths scaled by the farthest neighbor's distance).  Inside the neighbors' convex hull the first
    term vanishes, so ``sum_i w_i P_i = P_t`` holds up to the small ridge term, which makes the solution
    unique when L > 4 and prefers near neighbors (it is the theorem's error-bound term
    ``sum_i w_i ||P_t - P_i||^2`` in quadratic form).  Outside the hull the weights give the closest point
    of the hull.  A co-located neighbor gets all the weight; L = 1 gives weight 1.
    """
    T, L = mask.shape
    tgt = target.detach().double().cpu().numpy()
    pts = nbr.detach().double().cpu().numpy()
    msk = mask.detach().bool().cpu().numpy()
    out = np.zeros((T, L))
    for t in range(T):
        idx = np.flatnonzero(msk[t])
        rel = pts[t, idx] - tgt[t]  # [l, 3]
        d = np.linalg.norm(rel, axis=1)
        scale = d.max()
        if len(idx) == 1 or scale <= 1e-12:
            out[t, idx] = 1.0 / len(idx)
            continue
        rel, d = rel / scale, d / scale
        A = np.vstack([rel.T, sum_weight * np.ones((1, len(idx))), np.sqrt(ridge) * np.diag(d)])
        b = np.concatenate([np.zeros(3), [sum_weight], np.zeros(len(idx))])
        w, _ = nnls(A, b, maxiter=50 * len(idx))
        s = w.sum()
        out[t, idx] = w / s if s > 0 else 1.0 / len(idx)
    return torch.from_numpy(out).to(device=nbr.device, dtype=nbr.dtype)
