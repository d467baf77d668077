"""graf-interp through the real configs: the dataset part on the embedded measured scene, and every part on a
small ray-traced room."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from graf.app.config import CONF_DIR
from graf.case_studies.interpolation import run


def _cfg(tmp_path: Path, *overrides: str):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("interp", [f"paths.output_dir={tmp_path / 'out'}", *overrides])
    GlobalHydra.instance().clear()
    return cfg


def test_interp_on_the_measured_scene_fits_a_slope_per_weighting(tmp_path, capsys):
    cfg = _cfg(tmp_path, f"data_root={tmp_path / 'data'}", "interp.L=[1,4,16]")
    res = run(cfg)
    s = res["scenes"]["rfid_s23"]
    assert s["n_positions"] == 200 and "fine" not in s  # measured: no simulator, the dataset part only
    for w in ("barycentric", "idw"):
        fit = s["dataset"][w]["fit"]
        assert fit["n"] == 600 and fit["ci"][0] < fit["slope"] < fit["ci"][1]
        med = s["dataset"][w]["per_L"]
        assert med[1]["median_dp_m"] < med[4]["median_dp_m"] < med[16]["median_dp_m"]
    # L = 1: both weightings copy the nearest neighbor, so their errors are the same
    assert s["dataset"]["barycentric"]["per_L"][1] == s["dataset"]["idw"]["per_L"][1]
    out = tmp_path / "out"
    assert json.loads((out / "results.json").read_text())["scenes"]["rfid_s23"]["figure"] == "interp_rfid_s23.png"
    assert (out / "interp_rfid_s23.png").is_file()
    assert "rfid_s23" in capsys.readouterr().out


def test_interp_on_a_traced_room_measures_fine_scales_and_the_curvature(tmp_path, small_room_root, monkeypatch):
    cfg = _cfg(
        tmp_path,
        "scene=small_room",
        "sim_num_tx=24",
        f"data_root={small_room_root}",
        "interp.anchors=3",
        "interp.scales_wavelengths=[0.01,0.1,1.0]",
        "interp.kmap_spacing_m=1.5",
        "interp.L=[1,2]",
    )
    s = run(cfg)["scenes"]["small_room"]
    fine, k = s["fine"], s["curvature"]
    assert len(fine["barycentric"]["median_rmse"]) == 3
    assert fine["barycentric"]["median_rmse"][0] < fine["barycentric"]["median_rmse"][-1]  # closer is better
    assert len(k["K"]) == 3 and all(v > 0 for v in k["K"]) and -1.0 <= k["spearman_rho"] <= 1.0
    assert np.array(s["kmap"]["K"]).shape == (len(s["kmap"]["y"]), len(s["kmap"]["x"]))
    nf = s["kmap_near_far"]
    assert nf["near"]["n"] + nf["open"]["n"] + nf["inside_objects"] <= np.array(s["kmap"]["K"]).size
    # resumable per scene: a second invocation into the same folder keeps the finished scene, tracing nothing
    import graf.case_studies.interpolation as interp

    def no_trace(*a, **k):
        raise AssertionError("a finished scene was traced again")

    monkeypatch.setattr(interp, "fine_part", no_trace)
    figure = tmp_path / "out" / s["figure"]
    figure.unlink()  # a kept scene's figure is drawn again from its record
    again = run(cfg)
    assert again["complete"] and again["scenes"]["small_room"]["curvature"] == k
    assert figure.is_file()


def test_a_layout_variants_removed_objects_are_left_out_of_the_map():
    """conference_v2 removes chairs by setting them to null (graf-interp once failed on it)."""
    from types import SimpleNamespace

    from graf.case_studies.interpolation import footprints

    room = SimpleNamespace(objects={"chair": None, "table": {"center": [1, 2, 0.7], "size": [1, 1, 0.1]}})
    assert footprints(room) == [{"center": [1, 2, 0.7], "size": [1, 1, 0.1]}]
    assert footprints(SimpleNamespace(objects=None)) == [] and footprints(object()) == []


def test_the_k_map_is_split_into_points_near_walls_or_objects_and_open_space():
    from types import SimpleNamespace

    from graf.case_studies.interpolation import near_far
    from graf.geometry.shapes import Box, SceneGeometry

    xs = ys = [0.5, 1.5, 2.5, 3.5]  # a 4 x 4 m room, 1 m grid at z = 1
    K = [[10.0 if (x in (0.5, 3.5) or y in (0.5, 3.5)) else 1.0 for x in xs] for y in ys]  # high along the walls
    K[1][1] = 5.0  # (1.5, 1.5) sits in the table's box: left out
    room = SimpleNamespace(
        room={"size": [4.0, 4.0, 3.0]},
        geometry=SceneGeometry(boxes=[Box("table", np.array([1.5, 1.5, 1.0]), np.array([0.4, 0.4, 0.4]))]),
    )
    nf = near_far({"x": xs, "y": ys, "z": 1.0, "K": K}, room, margin=0.5)
    assert nf["inside_objects"] == 1 and nf["near"]["n"] + nf["open"]["n"] == 15
    assert nf["near"]["n"] == 12 and nf["open"]["n"] == 3  # the wall-side ring; the table is 1 m from the rest
    assert nf["near"]["median_K"] == 10.0 and nf["open"]["median_K"] == 1.0 and nf["near_over_open"] == 10.0
    assert near_far({}, room, 0.5) is None and near_far({"x": xs}, SimpleNamespace(), 0.5) is None
