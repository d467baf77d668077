"""graf-interp through the real configs: the dataset part on the embedded measured scene, and every part on a
small ray-traced room."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from graf.pipeline.config import CONF_DIR
from graf.pipeline.interp import run


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
    # L = 1: both weightings copy the nearest neighbour, so their errors are the same
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
    # resumable per scene: a second invocation into the same folder keeps the finished scene, tracing nothing
    import graf.pipeline.interp as interp

    def no_trace(*a, **k):
        raise AssertionError("a finished scene was traced again")

    monkeypatch.setattr(interp, "fine_part", no_trace)
    again = run(cfg)
    assert again["complete"] and again["scenes"]["small_room"]["curvature"] == k


def test_a_layout_variants_removed_objects_are_left_out_of_the_map():
    """conference_v2 removes chairs by setting them to null (graf-interp once failed on it)."""
    from types import SimpleNamespace

    from graf.pipeline.interp import footprints

    room = SimpleNamespace(objects={"chair": None, "table": {"center": [1, 2, 0.7], "size": [1, 1, 0.1]}})
    assert footprints(room) == [{"center": [1, 2, 0.7], "size": [1, 1, 0.1]}]
    assert footprints(SimpleNamespace(objects=None)) == [] and footprints(object()) == []
