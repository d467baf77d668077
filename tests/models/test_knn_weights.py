"""IDW and barycentric weights, and the interpolation theorem's behaviour on analytic fields."""

from __future__ import annotations

import numpy as np
import torch

from graf.models.knn.weights import barycentric_weights, idw_weights


def _simplex_ok(w, mask):
    assert bool((w >= -1e-12).all())
    assert bool((w[~mask] == 0).all())
    torch.testing.assert_close(w.sum(1), torch.ones(len(w), dtype=w.dtype))


def test_idw_basic_and_colocated():
    tgt = torch.zeros(2, 3, dtype=torch.float64)
    nbr = torch.tensor(
        [[[1.0, 0, 0], [2.0, 0, 0], [9.0, 0, 0]], [[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]], dtype=torch.float64
    )
    mask = torch.tensor([[True, True, False], [True, True, True]])
    w = idw_weights(tgt, nbr, mask)
    _simplex_ok(w, mask)
    torch.testing.assert_close(w[0, :2], torch.tensor([2 / 3, 1 / 3], dtype=torch.float64))
    assert w[1].tolist() == [1.0, 0.0, 0.0]  # zero distance takes all the weight


def test_barycentric_reproduces_target_inside_hull():
    g = torch.Generator().manual_seed(1)
    nbr = torch.rand(20, 8, 3, generator=g, dtype=torch.float64)
    tgt = nbr.mean(1)  # inside the hull
    mask = torch.ones(20, 8, dtype=torch.bool)
    w = barycentric_weights(tgt, nbr, mask)
    _simplex_ok(w, mask)
    scale = (nbr - tgt[:, None]).norm(dim=-1).max(1).values
    err = ((w[..., None] * nbr).sum(1) - tgt).norm(dim=1) / scale
    assert float(err.max()) < 2e-3


def test_barycentric_edge_cases():
    tgt = torch.zeros(3, 3, dtype=torch.float64)
    nbr = torch.tensor(
        [[[1.0, 0, 0], [2, 0, 0]], [[0.0, 0, 0], [1, 0, 0]], [[0.0, 0, 0], [0, 0, 0]]], dtype=torch.float64
    )
    mask = torch.tensor([[True, False], [True, True], [True, True]])
    w = barycentric_weights(tgt, nbr, mask)
    _simplex_ok(w, mask)
    assert w[0].tolist() == [1.0, 0.0]  # L = 1 (outside the hull: nearest point)
    assert float(w[1, 0]) > 0.999  # co-located neighbor
    assert w[2].tolist() == [0.5, 0.5]  # every neighbor at the target


def test_affine_field_is_exact_for_barycentric_not_idw():
    """If SS(P) is affine in P, the theorem's first-order term vanishes: barycentric interpolation is exact."""
    g = torch.Generator().manual_seed(2)
    A = torch.randn(3, 5, generator=g, dtype=torch.float64)
    nbr = torch.rand(30, 6, 3, generator=g, dtype=torch.float64)
    tgt = (torch.softmax(torch.randn(30, 6, generator=g, dtype=torch.float64), 1)[..., None] * nbr).sum(1)
    mask = torch.ones(30, 6, dtype=torch.bool)
    f = lambda p: p @ A  # noqa: E731
    e_bary = ((barycentric_weights(tgt, nbr, mask, ridge=1e-6)[..., None] * f(nbr)).sum(1) - f(tgt)).abs().max()
    e_idw = ((idw_weights(tgt, nbr, mask)[..., None] * f(nbr)).sum(1) - f(tgt)).abs().max()
    assert float(e_bary) < 1e-3 < float(e_idw)


def test_barycentric_error_is_quadratic_in_neighbor_distance():
    """Seed A.1: error <= K max_i |P_t - P_i|^2; on a smooth field the fitted log-log slope is ~2."""

    def field(p):
        return torch.stack([torch.sin(3 * p[..., 0]) * torch.cos(2 * p[..., 1]), torch.exp(p[..., 2])], -1)

    g = torch.Generator().manual_seed(3)
    tgt = torch.rand(40, 3, generator=g, dtype=torch.float64)
    # six neighbors at +-h along randomly rotated axes (random lengths in [0.5h, h]): the target is
    # inside their convex hull, as the theorem assumes
    rot, _ = torch.linalg.qr(torch.randn(40, 3, 3, generator=g, dtype=torch.float64))
    axes = torch.cat([torch.eye(3, dtype=torch.float64), -torch.eye(3, dtype=torch.float64)])
    lengths = 0.5 + 0.5 * torch.rand(40, 6, 1, generator=g, dtype=torch.float64)
    offsets = lengths * torch.einsum("kj,tij->tki", axes, rot)
    mask = torch.ones(40, 6, dtype=torch.bool)
    hs = np.array([0.2, 0.1, 0.05, 0.025, 0.0125])
    errs = []
    for h in hs:
        nbr = tgt[:, None] + h * offsets
        w = barycentric_weights(tgt, nbr, mask, ridge=1e-8)
        errs.append(float(((w[..., None] * field(nbr)).sum(1) - field(tgt)).abs().mean()))
    slope = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    assert 1.7 < slope < 2.3, (slope, errs)
