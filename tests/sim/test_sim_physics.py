"""Physics of the simulator, through the real Sionna RT tracer (CPU backend here)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate

from graf.app.config import CONF_DIR
from graf.bands import Band
from graf.metrics import psnr_per_sample
from graf.models.knn.weights import barycentric_weights
from graf.sim.scene import SimulatedScene

pytest.importorskip("sionna.rt")  # graf.sim (imported above) has configured the LLVM backend

BAND = Band("2.4ghz", 2.412e9)
GATEWAY = {"position": [0.0, 0.0, 1.5], "normal": [1, 0, 0], "x_axis": [0, 1, 0]}
TRACING = {
    "max_depth": 1,
    "los": True,
    "specular_reflection": True,
    "diffuse_reflection": False,
    "refraction": False,
    "diffraction": False,
    "samples_per_src": 10000,
    "max_num_paths_per_src": 40000,
    "seed": 1,
}
WALL = {"wall": {"material": "metal", "center": [3.0, 1.5, 1.5], "size": [6.0, 0.02, 3.0]}}  # a wall near the targets


def _scene(objects=None, max_depth=1) -> SimulatedScene:
    return SimulatedScene(
        name="physics",
        gateway=GATEWAY,
        objects=objects or {},
        transmitters={"count": 1, "min": [1, -1, 0], "max": [2, 1, 1]},
        tracing=dict(TRACING, max_depth=max_depth),
        array={"pattern": "cos"},
    )


def _spectra(scene: SimulatedScene, positions: np.ndarray) -> torch.Tensor:
    return scene.spectra(scene.tracer(BAND), scene.bartlett(BAND), positions)[1]


def _az_el(scene, points):
    """Azimuth, elevation (deg) of points seen from the gateway, in the gateway frame."""
    u = (np.asarray(points) - np.asarray(GATEWAY["position"])) @ scene.rotation.as_matrix()
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    return np.degrees(np.arctan2(u[:, 1], u[:, 0])) % 360, np.degrees(np.arcsin(u[:, 2]))


def _angle_deg(az1, el1, az2, el2):
    a1, e1, a2, e2 = map(np.radians, (az1, el1, az2, el2))
    c = np.sin(e1) * np.sin(e2) + np.cos(e1) * np.cos(e2) * np.cos(a1 - a2)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def test_line_of_sight_peaks_at_the_true_direction():
    scene = _scene(max_depth=0)
    rng = np.random.default_rng(0)
    pos = np.column_stack([rng.uniform(1.0, 6.0, 24), rng.uniform(-4, 4, 24), rng.uniform(0.2, 2.8, 24)])
    s = _spectra(scene, pos)
    az, el = _az_el(scene, pos)
    flat = s.view(len(pos), -1).argmax(1).numpy()
    pk_el, pk_az = flat // 360 + 1, flat % 360 + 1
    err = _angle_deg(az, el, pk_az, pk_el)
    assert err.max() <= 1.0, err


def test_one_reflecting_wall_adds_a_lobe_at_the_image_source():
    # A metal wall facing the array (plane x = 3, face at x = 2.99) and a transmitter almost in the array's
    # plane: the line of sight arrives near grazing (elevation 7 deg), the wall's reflection arrives from the
    # image source at elevation 54 deg, well apart from it.
    wall = {"wall": {"material": "metal", "center": [3.0, 0.0, 1.5], "size": [0.02, 12.0, 4.0]}}
    tx = np.array([[0.5, -4.0, 1.5]])
    image = np.array([[2 * 2.99 - 0.5, -4.0, 1.5]])
    with_wall = _spectra(_scene(wall), tx)[0].numpy()
    free = _spectra(_scene(), tx)[0].numpy()
    iaz, iel = _az_el(_scene(), image)
    r, c = int(round(iel[0])) - 1, int(round(iaz[0])) % 360 - 1
    rows, cols = np.meshgrid(np.arange(90), np.arange(360), indexing="ij")
    near = _angle_deg(cols + 1, rows + 1, iaz[0], iel[0]) <= 15
    pr, pc = np.unravel_index(int(np.argmax(np.where(near, with_wall, -1))), with_wall.shape)
    assert _angle_deg(pc + 1, pr + 1, iaz[0], iel[0]) <= 3.0  # the added lobe peaks at the image source
    assert with_wall[r, c] > 0.8 and free[r, c] < 0.5  # and it is not there without the wall


def _octahedra(centres, h, seed=0):
    g = torch.Generator().manual_seed(seed)
    rot, _ = torch.linalg.qr(torch.randn(len(centres), 3, 3, generator=g, dtype=torch.float64))
    axes = torch.cat([torch.eye(3, dtype=torch.float64), -torch.eye(3, dtype=torch.float64)])
    return torch.as_tensor(centres)[:, None, :] + h * torch.einsum("kj,tij->tki", axes, rot)


def _interpolation_errors(scene, centres, hs):
    errs = []
    for h in hs:
        nbr = _octahedra(centres, h)
        pts = np.concatenate([centres, nbr.reshape(-1, 3).numpy()])
        s = _spectra(scene, pts).double()
        tgt, src = s[: len(centres)], s[len(centres) :].view(len(centres), 6, 90, 360)
        w = barycentric_weights(
            torch.as_tensor(centres), nbr, torch.ones(len(centres), 6, dtype=torch.bool), ridge=1e-8
        )
        pred = torch.einsum("tl,tlhw->thw", w, src)
        errs.append(float((pred - tgt).abs().mean()))
    return np.array(errs)


def test_barycentric_interpolation_error_is_quadratic_in_free_space_and_larger_near_obstacles():
    centres = np.array([[3.0, 0.4, 1.2], [2.5, -0.8, 1.8], [4.0, 0.2, 0.9], [3.5, -0.3, 2.1]])
    hs = np.array([0.04, 0.02, 0.01, 0.005])
    free = _interpolation_errors(_scene(max_depth=0), centres, hs)
    slope = np.polyfit(np.log(hs), np.log(free), 1)[0]
    assert abs(slope - 2.0) <= 0.3, (slope, free)
    near = _interpolation_errors(_scene(WALL), centres, hs[1:3])
    assert np.all(near > 3 * free[1:3]), (near, free[1:3])


def test_default_sample_budget_is_converged_on_a_small_scene():
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="simulate", overrides=["scene=small_room", "band=2.4ghz"])
    GlobalHydra.instance().clear()
    scene, band = instantiate(cfg.scene.small_room), instantiate(cfg.band)
    pos = scene.positions(32)
    runs = []
    for factor in (1, 2):
        tracer = scene.tracer(
            band,
            samples_per_src=factor * scene.tracing["samples_per_src"],
            max_num_paths_per_src=factor * scene.tracing["max_num_paths_per_src"],
        )
        _, spectra, n_paths = scene.spectra(tracer, scene.bartlett(band), pos)
        assert n_paths.min() > 10  # a furnished room at depth 3: many paths per link
        runs.append(spectra)
    psnr = psnr_per_sample(runs[0], runs[1])
    assert float(psnr.min()) >= 40.0, psnr


@pytest.mark.parametrize("band_name", ["915mhz", "3ghz"])
def test_low_and_high_bands_follow_the_wavelength(band_name):
    """Band extremes: the array pitch follows the wavelength, materials outside their ITU range are
    extrapolated and flagged, and spectra stay finite and normalised."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="simulate", overrides=["scene=small_room", f"band={band_name}"])
    GlobalHydra.instance().clear()
    scene, band = instantiate(cfg.scene.small_room), instantiate(cfg.band)
    pitch = np.diff(np.unique(scene.antenna_positions(band)[:, 0]))
    np.testing.assert_allclose(pitch, band.wavelength / 2)
    tracer = scene.tracer(band)
    _, s, n = scene.spectra(tracer, scene.bartlett(band), scene.positions(8))
    assert torch.isfinite(s).all() and n.min() > 0
    torch.testing.assert_close(s.amax(dim=(1, 2)), torch.ones(8))
    flags = {m["itu_type"]: m["extrapolated"] for m in tracer.material_table()}
    assert flags["concrete"] is (band_name == "915mhz")  # ITU-R P.2040 tabulates concrete from 1 GHz
