"""The 4x4 array and Bartlett beamformer (no ray tracing needed): conventions and array physics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import brentq

from graf.geometry.grid import grid_directions
from graf.sim.array import Bartlett, array_positions, pattern_gain, rotation_from_axes


def _single_path_spectrum(u: np.ndarray, wavelength: float, pitch_wavelengths: float = 0.5, pattern="iso"):
    b = Bartlett(array_positions(wavelength, pitch_wavelengths=pitch_wavelengths), wavelength)
    gains = torch.ones(1, 1, dtype=torch.complex128)
    h = b.channels(gains, torch.as_tensor(u, dtype=torch.float64).view(1, 1, 3), pattern)
    return b.spectra(h)[0]


def _direction(az_deg, el_deg):
    a, e = math.radians(az_deg), math.radians(el_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def test_nerf2_array_geometry():
    pos = array_positions(0.32, pitch_wavelengths=0.5)
    np.testing.assert_allclose(sorted(set(np.round(pos[:, 0], 6))), [-0.24, -0.08, 0.08, 0.24])
    assert np.all(pos[:, 2] == 0)


def test_grid_convention_row_is_elevation_column_is_azimuth():
    d = grid_directions().view(90, 360, 3)
    np.testing.assert_allclose(d[0, 0].numpy(), _direction(1, 1), atol=1e-12)
    np.testing.assert_allclose(d[89, 359].numpy(), _direction(360, 90), atol=1e-12)
    np.testing.assert_allclose(d[29, 119].numpy(), _direction(120, 30), atol=1e-12)


@pytest.mark.parametrize("az,el", [(30.0, 45.0), (200.0, 60.0), (300.0, 20.0), (90.0, 75.0)])
def test_single_path_peaks_at_its_direction(az, el):
    s = _single_path_spectrum(_direction(az, el), wavelength=0.124)
    r, c = np.unravel_index(int(torch.argmax(s)), s.shape)
    assert abs(r + 1 - el) <= 1 and min(abs(c + 1 - az), 360 - abs(c + 1 - az)) <= 1
    assert float(s.max()) == 1.0 and float(s.min()) == 0.0


def _measured_width_deg(wavelength, pitch_wavelengths):
    """Full half-power width (amplitude >= 1/sqrt(2) of the peak) of the main lobe of a broadside path,
    measured on the elevation cut at azimuth 1 deg (the grid's resolution is 1 deg)."""
    s = _single_path_spectrum(_direction(0.0, 90.0), wavelength, pitch_wavelengths)
    cut = s[:, 0].numpy()[::-1]  # elevation 90, 89, ... (peak first)
    n = int(np.argmax(cut < 1 / math.sqrt(2)))  # rows inside the half-power lobe
    return 2 * n - 1


def _predicted_width_deg(wavelength, pitch_m, N=4):
    """Uniform N-element array: |sin(N psi / 2) / (N sin(psi / 2))| = 1/sqrt(2), psi = k d cos(elevation)."""
    psi = brentq(lambda x: abs(math.sin(N * x / 2) / (N * math.sin(x / 2))) - 1 / math.sqrt(2), 1e-6, 2 * math.pi / N)
    return 2 * (90 - math.degrees(math.acos(psi / (2 * math.pi / wavelength * pitch_m))))


def test_main_lobe_width_scales_with_wavelength_as_the_array_predicts():
    # NeRF2's fixed 0.16 m pitch: the lobe widens in proportion to the wavelength
    lams = (0.124, 0.1666, 0.3276)
    widths = [_measured_width_deg(lam, 0.16 / lam) for lam in lams]
    for lam, w in zip(lams, widths):
        assert abs(w - _predicted_width_deg(lam, 0.16)) <= 2.0, (lam, w, _predicted_width_deg(lam, 0.16))
    assert widths[0] < widths[1] < widths[2]
    assert abs(widths[2] / widths[0] - lams[2] / lams[0]) < 0.25 * lams[2] / lams[0]
    # half-wavelength pitch at every band (the simulator's default): the same lobe in angle
    same = [_measured_width_deg(lam, 0.5) for lam in (0.0999, 0.124, 0.1666, 0.3276)]
    assert max(same) - min(same) <= 1
    assert abs(same[0] - _predicted_width_deg(0.124, 0.062)) <= 2.0


def test_pattern_decides_what_arrives_from_behind():
    u_front, u_back = _direction(40, 30), _direction(40, 30) * np.array([1, 1, -1])
    assert float(pattern_gain(torch.tensor(u_back), "cos")) == 0.0
    assert float(pattern_gain(torch.tensor(u_back), "front")) == 0.0
    s_iso = _single_path_spectrum(u_back, 0.124, pattern="iso")
    s_front = _single_path_spectrum(u_front, 0.124, pattern="iso")
    torch.testing.assert_close(s_iso, s_front)  # a planar array folds the back path onto its mirror
    assert float(_single_path_spectrum(u_back, 0.124, pattern="cos").abs().max()) == 0.0  # no paths: zeros
    with pytest.raises(ValueError, match="unknown antenna pattern"):
        pattern_gain(torch.tensor(u_back), "dipole")


def test_gateway_rotation_maps_normal_to_local_z():
    R = rotation_from_axes([1, 0, 0], [0, 1, 0]).as_matrix()
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    with pytest.raises(ValueError, match="parallel"):
        rotation_from_axes([1, 0, 0], [2, 0, 0])
