"""The building blocks of issue 24's case studies: the power-law fit of the interpolation theorem and the
angle-of-arrival estimator, on cases whose answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from graf.case_studies.aoa import angular_error, arrival_direction, direction_to_angles, peak_direction
from graf.case_studies.interpolation import fit_power_law
from graf.sim.array import Bartlett, array_positions


def test_the_power_law_fit_recovers_a_known_exponent_and_its_interval_covers_it():
    rng = np.random.default_rng(0)
    x = np.geomspace(0.01, 1.0, 200)
    y = 3.0 * x**2 * np.exp(0.2 * rng.standard_normal(x.size))  # multiplicative noise: Gaussian on log axes
    fit = fit_power_law(x, y)
    assert abs(fit.slope - 2.0) < 0.05 and fit.ci[0] < 2.0 < fit.ci[1]
    assert abs(10**fit.intercept - 3.0) < 0.3 and fit.n == 200 and fit.r2 > 0.95
    assert fit.ci[1] - fit.ci[0] < 0.1
    exact = fit_power_law(x, 0.5 * x**1.5)
    assert exact.slope == pytest.approx(1.5, abs=1e-9) and exact(0.3) == pytest.approx(0.5 * 0.3**1.5)


def test_the_power_law_fit_leaves_out_zeros_and_refuses_too_few_points():
    fit = fit_power_law([0.1, 0.2, 0.0, 0.4, 0.8], [0.01, 0.04, 0.0, 0.16, 0.64])  # a zero error has no log
    assert fit.n == 4 and fit.slope == pytest.approx(2.0)
    with pytest.raises(ValueError, match="at least 3"):
        fit_power_law([0.1, 0.2, 0.0], [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="all x are equal"):
        fit_power_law([0.1, 0.1, 0.1], [1.0, 2.0, 3.0])


def _free_space_spectrum(el: float, az: float, wavelength: float = 0.125) -> np.ndarray:
    """The Bartlett spectrum of one plane wave (free space, line of sight only) from (el, az)."""
    bart = Bartlett(array_positions(wavelength), wavelength)
    e, a = math.radians(el), math.radians(az)
    u = torch.tensor([[[math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]]], dtype=torch.float64)
    h = bart.channels(torch.ones(1, 1, dtype=torch.complex64), u, pattern="cos")
    return bart.spectra(h)[0].numpy()


@pytest.mark.parametrize(("el", "az"), [(35.0, 120.0), (62.3, 359.6), (20.0, 0.7), (48.5, 210.25)])
def test_the_aoa_of_a_line_of_sight_path_in_free_space_is_found_within_one_degree(el, az):
    est_el, est_az = peak_direction(_free_space_spectrum(el, az))
    assert angular_error(est_el, est_az, el, az) < 1.0  # off-grid angles and the azimuth seam included


def test_the_geometric_angle_of_arrival_follows_the_grid_convention():
    rot = np.eye(3)  # gateway frame = world frame
    el, az = arrival_direction([[1.0, 1.0, math.sqrt(2.0)], [-1.0, 0.0, 0.0], [0.0, -2.0, 2.0]], [0.0, 0.0, 0.0], rot)
    assert el == pytest.approx([45.0, 0.0, 45.0]) and az == pytest.approx([45.0, 180.0, 270.0])
    # a transmitter behind the array plane is seen at its mirror image (a planar array cannot tell them apart)
    e2, a2 = direction_to_angles([0.0, 1.0, -1.0])
    assert float(e2) == pytest.approx(45.0) and float(a2) == pytest.approx(90.0)
    with pytest.raises(ValueError, match="gateway's own position"):
        arrival_direction([[0.0, 0.0, 0.0]], [0.0, 0.0, 0.0], rot)


def test_the_peak_estimator_refuses_a_wrong_shape_or_nan():
    with pytest.raises(ValueError, match=r"\[90, 360\]"):
        peak_direction(np.zeros((90, 180)))
    bad = np.zeros((90, 360))
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        peak_direction(bad)
    flat = np.zeros((90, 360))  # all zero: the first pixel, not refined
    assert peak_direction(flat) == (1.0, 1.0)


def _smooth_field(pos: np.ndarray, pixels: int = 40, seed: int = 1) -> np.ndarray:
    """A field whose every pixel is a quadratic of the position: second derivatives 2 c_p along every axis."""
    rng = np.random.default_rng(seed)
    a, b, c = rng.random(pixels), rng.standard_normal((3, pixels)), 0.5 + rng.random(pixels)
    return a + pos @ b + (pos**2).sum(axis=1, keepdims=True) * c


def test_barycentric_interpolation_error_grows_as_dp_squared_and_idw_as_dp():
    from graf.case_studies.interpolation import interpolation_errors

    rng = np.random.default_rng(0)
    dp, err = {"barycentric": [], "idw": []}, {"barycentric": [], "idw": []}
    for spacing in (0.02, 0.05, 0.1, 0.2, 0.4):  # jittered grids ever coarser: dP spans more than a decade
        g = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3).astype(float)
        pos = (g + 0.3 * rng.standard_normal(g.shape)) * spacing
        inner = np.flatnonzero(np.all((g > 0) & (g < 5), axis=1))  # targets inside the cloud
        for w in dp:
            r = interpolation_errors(pos, _smooth_field(pos), L=12, weighting=w, targets=inner)
            dp[w].append(r["dp_max"])
            err[w].append(r["rmse"])
    bary = fit_power_law(np.concatenate(dp["barycentric"]), np.concatenate(err["barycentric"]))
    # IDW does not reproduce a linear field: its error is first order while dP is small (the three finest grids;
    # on the coarser ones the quadratic term catches up)
    idw = fit_power_law(np.concatenate(dp["idw"][:3]), np.concatenate(err["idw"][:3]))
    assert 1.8 < bary.slope < 2.2 and bary.ci[0] < 2.0 < bary.ci[1], bary
    assert 0.8 < idw.slope < 1.2, idw


def test_the_curvature_of_a_quadratic_field_is_its_second_derivative():
    from graf.case_studies.interpolation import curvature

    rng = np.random.default_rng(1)  # _smooth_field's draws for seed 1: a, b, then c
    rng.random(40), rng.standard_normal((3, 40))
    c = 0.5 + rng.random(40)
    k = curvature(lambda p: _smooth_field(p), [0.3, -0.2, 0.1], h=1e-3)
    assert k == pytest.approx(float(np.sqrt(np.mean((2 * c) ** 2))), rel=1e-4)
    with pytest.raises(ValueError, match="step"):
        curvature(lambda p: _smooth_field(p), [0, 0, 0], h=0.0)


def _wave_field(pos: np.ndarray, k: float = 50.0, pixels: int = 30, seed: int = 2) -> np.ndarray:
    """A field that is smooth below 1/k metres and decorrelates above (plane waves of wavenumber k, as a
    2.4 GHz spectrum decorrelates within centimetres)."""
    rng = np.random.default_rng(seed)
    dirs = rng.standard_normal((pixels, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return 0.5 + 0.5 * np.cos(k * pos @ dirs.T + rng.uniform(0, 2 * np.pi, pixels))


def test_fine_scale_clusters_find_the_quadratic_regime_and_where_it_ends():
    from graf.case_studies.interpolation import cluster_errors, local_slopes, quadratic_up_to

    anchors = np.random.default_rng(3).uniform(-1, 1, (12, 3))
    scales = np.geomspace(1e-3, 1.0, 7)  # (below a millimetre the barycentric ridge term's tiny bias shows)
    smooth = cluster_errors(_smooth_field, anchors, scales)
    assert np.allclose(smooth["dp_max"], smooth["scale"])
    _, slopes = local_slopes(smooth["scale"], smooth["rmse_barycentric"])
    assert np.all(np.abs(slopes - 2.0) < 0.15)  # the quadratic field: slope 2 at every scale
    assert quadratic_up_to(smooth["scale"], smooth["rmse_barycentric"]) == pytest.approx(1.0)
    _, idw = local_slopes(smooth["scale"], smooth["rmse_idw"])
    assert 0.6 < np.median(idw[:4]) < 1.4  # IDW does not reproduce the linear part: first order
    wave = cluster_errors(_wave_field, anchors, scales)
    up_to = quadratic_up_to(wave["scale"], wave["rmse_barycentric"])
    assert up_to is not None and 1e-3 <= up_to <= 0.1  # quadratic below ~1/k = 0.02 m, not beyond
    _, ws = local_slopes(wave["scale"], wave["rmse_barycentric"])
    assert ws[0] > 1.8 and ws[-1] < 0.5  # decorrelated at the largest scales


def test_the_curvature_map_is_the_curvature_at_every_point():
    from graf.case_studies.interpolation import curvature, curvature_map

    pts = np.random.default_rng(4).uniform(-1, 1, (5, 3))
    k = curvature_map(_wave_field, pts, h=1e-3)
    assert k.shape == (5,)
    assert k == pytest.approx([curvature(_wave_field, p, 1e-3) for p in pts], rel=1e-9)
    # traced in chunks (memory bounded), the same values; a call never holds more than a chunk's stencils
    calls = []

    def field(x):
        calls.append(len(x))
        return _wave_field(x)

    assert curvature_map(field, pts, h=1e-3, chunk=2) == pytest.approx(k, rel=1e-12)
    assert calls == [14, 14, 7]
