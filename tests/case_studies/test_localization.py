"""Issue 24, part 4's building blocks: the localizer's shapes and its azimuth wrap, and splits that never train on
a test position or its synthesized copy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from graf.case_studies.localization import (
    SpectrumLocalizer,
    check_disjoint,
    denormalise,
    normalise,
    synthetic_positions,
)
from graf.errors import ConfigError


def test_the_localizer_maps_spectra_to_positions_and_wraps_in_azimuth():
    torch.manual_seed(0)
    net = SpectrumLocalizer()
    x = torch.rand(4, 90, 360)
    assert net(x).shape == (4, 3)

    def first_layer(s):
        return net.features(s, layers=1)

    # circular padding: rolling the spectrum 4 pixels in azimuth (one output column) rolls the features by
    # exactly one column, the seam included, so a pattern across 360 -> 1 deg is seen as anywhere else
    assert torch.allclose(first_layer(torch.roll(x, 4, dims=2)), torch.roll(first_layer(x), 1, dims=3), atol=1e-6)
    loss = net(x).pow(2).mean()
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_synthetic_positions_keep_away_from_every_test_position():
    rng = np.random.default_rng(0)
    lo, hi = np.zeros(3), np.ones(3)
    test = rng.uniform(lo, hi, (30, 3))
    syn = synthetic_positions(lo, hi, 500, test, min_gap=0.05, seed=1)
    assert syn.shape == (500, 3) and (syn >= lo).all() and (syn <= hi).all()
    check_disjoint(syn, test, 0.05, "synthesized set")  # by construction: passes
    with pytest.raises(ConfigError, match="within 0.05 m of a test position"):
        check_disjoint(np.vstack([syn, test[3] + 0.01]), test, 0.05, "synthesized set")
    with pytest.raises(ConfigError, match="lower min_gap"):
        synthetic_positions(lo, hi, 10, rng.uniform(lo, hi, (2000, 3)), min_gap=0.5)


def test_normalised_coordinates_round_trip():
    lo, hi = np.array([1.0, -2.0, 0.5]), np.array([3.0, 2.0, 1.5])
    p = np.array([[2.0, 0.0, 1.0], [1.0, -2.0, 1.5]])
    assert normalise(p, lo, hi) == pytest.approx(np.array([[0.0, 0.0, 0.0], [-1.0, -1.0, 1.0]]))
    assert denormalise(normalise(p, lo, hi), lo, hi) == pytest.approx(p)
