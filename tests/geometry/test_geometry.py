"""The ground floor's geometry (graf.geometry): positional encoding, the normalisation of positions into a
scene's bounds, the spectrum grid's directions, samples per ray and the pixels of a step."""

from __future__ import annotations

import math

import torch

from graf.geometry.encoding import PositionalEncoding, normalize_positions


def test_positional_encoding_and_normalisation():
    pe = PositionalEncoding(10)
    assert pe(torch.zeros(5, 3)).shape == (5, 63) and pe(torch.zeros(2, 7, 4)).shape == (2, 7, 84)
    x = torch.tensor([[0.25, -0.5, 1.0]])
    y = pe(x)
    assert torch.equal(y[:, :3], x)
    k = 3  # sin(2^k pi x) of the second coordinate sits after the 3 inputs at (coord * F + k)
    assert torch.allclose(y[0, 3 + 1 * 10 + k], torch.sin(torch.tensor(2.0**k * math.pi * -0.5)), atol=1e-6)
    assert torch.allclose(y[0, 33 + 1 * 10 + k], torch.cos(torch.tensor(2.0**k * math.pi * -0.5)), atol=1e-6)
    bounds = torch.tensor([[[-1.0, 0.0, 0.0], [3.0, 1.0, 2.0]]])
    corners = torch.tensor([[[-1.0, 0.0, 0.0], [3.0, 1.0, 2.0], [1.0, 0.5, 1.0]]])
    n = normalize_positions(corners, bounds)
    assert torch.allclose(n[0, 2], torch.zeros(3)) and n.abs().max() == 1.0  # centre -> 0, largest axis -> +-1
    assert torch.allclose(n[0, 1] - n[0, 0], (corners[0, 1] - corners[0, 0]) / 2.0)  # one scale for all axes


def test_the_grid_and_the_rays_follow_the_convention_and_the_scene():
    """Pixel ``r * 360 + c`` is elevation r + 1 deg, azimuth c + 1 deg; samples per ray are the ray's length in
    wavelengths, capped and at least 1 (a zero-length ray keeps one); a step's pixels are distinct and reproducible."""
    from graf.geometry.grid import N_AZIMUTH, grid_directions
    from graf.geometry.rays import num_samples, random_pixels

    d = grid_directions()
    assert d.shape == (32400, 3) and torch.allclose(d.norm(dim=-1), torch.ones(32400, dtype=torch.float64))
    r, c = 29, 89  # elevation 30 deg, azimuth 90 deg: straight along +y, tilted up by 30 deg
    assert torch.allclose(d[r * N_AZIMUTH + c], torch.tensor([0.0, math.cos(math.pi / 6), 0.5], dtype=d.dtype))
    lengths, wavelength = torch.tensor([0.0, 0.3, 1.0, 100.0]), torch.tensor([0.125, 0.125, 0.125, 0.125])
    assert num_samples(lengths, wavelength, 64) == [1, 3, 8, 64]
    assert num_samples(torch.tensor([1.0]), torch.tensor([0.03]), 64) == [34]  # a higher band: more samples
    px = random_pixels(2, 100, step=7)
    assert px.shape == (2, 50) and all(len(set(row.tolist())) == 50 for row in px)
    assert torch.equal(px, random_pixels(2, 100, step=7)) and not torch.equal(px, random_pixels(2, 100, step=8))
