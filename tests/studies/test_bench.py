"""graf-bench, composed from the real ``bench`` config with tiny models on CPU (seconds, not minutes)."""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import HydraException

import graf.studies.bench as bench_cli
from graf.app.config import CONF_DIR
from graf.errors import ConfigError
from graf.studies.bench import bench, ensure_simulated, scene_and_band
from graf.studies.bench_load import Competitor, LoadMeter, disturbances, spread
from graf.studies.bench_report import add_ratios

REQUIRED = {
    "method",
    "preset",
    "scene",
    "samples_per_ray",
    "infer_s_per_spectrum",
    "train_s_per_step",
    "train_rays_per_s",
    "peak_mb_train",
    "peak_mb_infer",
    "peak_mb",
    "parameters",
    "checkpoint_mb",
    "infer_ratio_to_graf",
    "train_ratio_to_graf",
    "infer_load_cores",
    "train_load_cores",
    "infer_spread",
    "train_spread",
    "disturbed",
}
TINY_GRAF = ("models.graf_cpu.max_samples=4", "models.graf_cpu.encoder_widths=[4,8,8,8]")


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


@pytest.fixture
def bench_cfg(tmp_path):
    def _compose(*overrides: str):
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(
                config_name="bench",
                overrides=[
                    f"paths.output_dir={tmp_path / 'out'}",
                    f"data_root={tmp_path / 'data'}",
                    "quick=true",
                    "threads=1",
                    *overrides,
                ],
            )
        GlobalHydra.instance().clear()
        return cfg

    return _compose


def _results(cfg) -> dict:
    return json.loads((Path(cfg.paths.output_dir) / "results.json").read_text())


def test_the_default_config_benchmarks_every_method_on_a_real_and_a_simulated_scene(bench_cfg):
    cfg = bench_cfg()
    assert set(cfg.models) == {
        "graf",
        "graf_cpu",
        "graf_cpu_ray_weights",
        "nerf2",
        "nerf2_cpu",
        "rf_gs",
        "knn_dl",
        "knn",
    }
    assert cfg.bench.compete is False
    assert cfg.scenes.real.name == "rfid_s23" and cfg.bands.real.name == "915mhz"
    assert cfg.scenes.room.name == "conference_v1" and cfg.bands.room.name == "2.4ghz"
    assert cfg.bench.rays_per_step == 5120 and cfg.bench.sim_num_tx == 64
    assert scene_and_band(cfg, "room")[0].num_tx == 64  # the limited dataset <band>-n64.h5
    assert scene_and_band(cfg, "real")[0].get("num_tx") is None


def test_quick_run_on_the_embedded_scene_writes_rows_table_and_ratios(bench_cfg):
    cfg = bench_cfg("bench.scenes=[real]", "bench.models=[graf_cpu,knn_dl,knn]", *TINY_GRAF)
    result = bench(cfg)
    r = _results(cfg)
    assert r["rows"] == json.loads(json.dumps(result["rows"]))
    assert r["threads"] == 1 and r["torch"] == torch.__version__ and r["device_type"] == "cpu" and r["device"]
    assert r["spectra_timed"] == 1 and r["train_steps_timed"] == 1 and r["quick"] is True and "config" in r
    assert r["ratio_base"] == {"rfid_s23": "graf_cpu"}  # no paper-size graf row: the first GRaF row
    rows = {x["preset"]: x for x in r["rows"]}
    assert list(rows) == ["graf_cpu", "knn_dl", "knn"]
    for x in rows.values():
        assert REQUIRED <= set(x) and not x.get("error") and x["scene"] == "rfid_s23"
    g, dl, knn = rows["graf_cpu"], rows["knn_dl"], rows["knn"]
    for key in ("infer_s_per_spectrum", "train_s_per_step", "train_rays_per_s"):
        assert math.isfinite(g[key]) and g[key] > 0
    assert g["method"] == "graf" and g["train_rays_per_step"] == 5120  # the paper's rays per step, forced
    assert 0 < g["samples_per_ray"] <= 4 and g["parameters"] > 0 and g["checkpoint_mb"] > 0
    assert g["peak_mb"] == max(g["peak_mb_train"], g["peak_mb_infer"]) and g["peak_mb_train"] >= 0
    assert g["infer_ratio_to_graf"] == 1.0 and g["train_ratio_to_graf"] == 1.0
    assert dl["train_rays_per_step"] == 32400 * dl["train_batch_size"] and dl["samples_per_ray"] is None
    assert dl["train_ratio_to_graf"] == pytest.approx(dl["train_s_per_step"] / g["train_s_per_step"], rel=1e-3)
    assert knn["train_s_per_step"] is None and knn["train_rays_per_s"] is None and knn["train_ratio_to_graf"] is None
    assert knn["parameters"] == 0 and knn["samples_per_ray"] is None
    assert knn["infer_ratio_to_graf"] == pytest.approx(
        knn["infer_s_per_spectrum"] / g["infer_s_per_spectrum"], rel=1e-3, abs=1e-4
    )
    md = (Path(cfg.paths.output_dir) / "bench.md").read_text()
    assert "| rfid_s23 | graf_cpu | graf |" in md and "cpu, 1 threads" in md


def test_the_ratio_base_is_the_paper_size_graf_row_of_the_same_scene():
    def row(preset, method, scene, t, s=None, error=None):
        return {
            "preset": preset,
            "method": method,
            "scene": scene,
            "infer_s_per_spectrum": t,
            "train_s_per_step": s,
            "error": error,
        }

    rows = [
        row("graf_cpu", "graf", "a", 2.0, 1.0),
        row("graf", "graf", "a", 4.0, 2.0),
        row("knn", "knn", "a", 1.0),
        row("graf", "graf", "b", 1.0, error="boom"),
        row("graf_cpu", "graf", "b", 0.5, 0.25),
        row("knn", "knn", "c", 1.0),
    ]
    assert add_ratios(rows) == {"a": "graf", "b": "graf_cpu", "c": None}
    assert [r["infer_ratio_to_graf"] for r in rows] == [0.5, 1.0, 0.25, None, 1.0, None]
    assert [r["train_ratio_to_graf"] for r in rows] == [0.5, 1.0, None, None, 1.0, None]


def test_a_missing_simulated_dataset_is_simulated_first_and_a_failed_row_does_not_stop_the_others(
    bench_cfg, monkeypatch
):
    calls = []
    monkeypatch.setattr(bench_cli, "simulate", lambda cfg: calls.append(cfg))  # records, makes nothing
    cfg = bench_cfg("bench.models=[knn,bad]", "+model@models.bad=graf_cpu", "models.bad.d_model=0")
    bench(cfg)
    assert len(calls) == 1
    sim = calls[0]
    assert sim.scene.name == "conference_v1" and sim.band.name == "2.4ghz" and sim.sim.num_tx == 64
    assert sim.data_root == cfg.data_root and sim.sim.overwrite is False
    assert Path(sim.paths.output_dir) == Path(cfg.paths.output_dir) / "simulate" / "room"
    rows = {(x["scene"], x["preset"]): x for x in _results(cfg)["rows"]}
    assert set(rows) == {("rfid_s23", "knn"), ("rfid_s23", "bad"), ("conference_v1", "knn"), ("conference_v1", "bad")}
    assert not rows["rfid_s23", "knn"].get("error") and rows["rfid_s23", "knn"]["infer_s_per_spectrum"] > 0
    assert "GRaF sizes must be positive" in rows["rfid_s23", "bad"]["error"]  # the model cannot be built
    for m in ("knn", "bad"):  # the fake simulation made no file: the scene's rows say why
        assert "DataFormatError" in rows["conference_v1", m]["error"] and REQUIRED <= set(rows["conference_v1", m])


def test_an_existing_simulated_dataset_is_not_simulated_again(bench_cfg, monkeypatch):
    calls = []
    monkeypatch.setattr(bench_cli, "simulate", lambda cfg: calls.append(cfg))
    cfg = bench_cfg()
    scene_cfg, band_cfg = scene_and_band(cfg, "room")
    path = Path(cfg.data_root) / "sim" / "conference_v1" / "2.4ghz-n64.h5"
    assert ensure_simulated(cfg, "room", scene_cfg, band_cfg) == path and len(calls) == 1
    path.parent.mkdir(parents=True)
    path.touch()
    assert ensure_simulated(cfg, "room", scene_cfg, band_cfg) == path and len(calls) == 1
    assert ensure_simulated(cfg, "real", *scene_and_band(cfg, "real")) is None and len(calls) == 1


def test_unknown_models_and_scenes_are_config_errors(bench_cfg):
    with pytest.raises(HydraException, match="no_such_model"):
        bench_cfg("model@models.graf=no_such_model")
    with pytest.raises(HydraException, match="no_such_scene"):
        bench_cfg("scene_catalog@scenes.room=no_such_scene")
    with pytest.raises(ConfigError, match="nope"):
        bench(bench_cfg("bench.models=[nope]"))
    with pytest.raises(ConfigError, match=r"\+band@bands.office"):
        bench(bench_cfg("+scene_catalog@scenes.office=office_v1"))


@pytest.mark.parametrize(
    "override, says",
    [
        ("threads=0", "threads=0: must be a whole number >= 1 or null"),  # torch's traceback
        ("threads=1.5", "threads=1.5: must be a whole number >= 1 or null"),
        ("bench.compete=maybe", "bench.compete=maybe: must be true or false"),  # it ran as true
        ("quick=no", "quick=no: must be true or false"),
        ("quick=false bench.spectra=2.5", "bench.spectra=2.5: must be a whole number >= 1"),
    ],
)
def test_threads_and_switches_are_checked_before_anything_runs(bench_cfg, override, says):
    with pytest.raises(ConfigError, match=f"^{re.escape(says)}$"):
        bench(bench_cfg(*override.split()))


def test_graf_bench_threads_0_is_one_line_and_exit_code_2(monkeypatch, capsys, tmp_path):
    from graf.cli.studies import bench as graf_bench
    from tests.app.test_entry_points import _main

    code, _, err = _main(monkeypatch, capsys, graf_bench.main, "threads=0", f"hydra.run.dir={tmp_path}")
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("[")]
    assert code == 2 and "Traceback" not in err, err
    assert lines[0] == "error: threads=0: must be a whole number >= 1 or null", err


def test_the_load_meter_sees_a_competing_process_and_the_row_is_flagged():
    """Other processes' CPU time is measured, a competing process shows up in it, and a row with that load or a
    wide spread of repeated timings is flagged (why, in words)."""
    with Competitor(), LoadMeter() as busy:
        time.sleep(1.0)
    assert busy.cores is not None and busy.cores > 0.5  # the competitor took about one core
    row = {"infer_load_cores": busy.cores, "infer_spread": 0.02, "train_load_cores": None, "train_spread": None}
    flags = disturbances(row)
    assert len(flags) == 1 and flags[0].startswith("infer: other processes used")
    assert disturbances({"infer_load_cores": 0.0, "infer_spread": 0.4}) == [
        "infer: repeated timings spread 40% (limit 15%)"
    ]
    assert spread([1.0]) is None and spread([1.0, 1.2, 1.1]) == pytest.approx(0.2 / 1.1, rel=1e-3)


def test_compete_times_each_row_again_beside_a_busy_process(bench_cfg):
    cfg = bench_cfg("bench.scenes=[real]", "bench.models=[graf_cpu,knn]", "bench.compete=true", *TINY_GRAF)
    bench(cfg)
    r = _results(cfg)
    assert r["compete"] is True and r["disturbance_limits"] == {"load_cores": 0.2, "spread": 0.15}
    for row in r["rows"]:
        loaded_load = row["infer_load_cores_loaded"]  # None: a phase too short for /proc's 10 ms ticks
        assert row["infer_s_per_spectrum_loaded"] > 0 and (loaded_load is None or loaded_load > 0.5)
        assert row["infer_slowdown"] == pytest.approx(
            row["infer_s_per_spectrum_loaded"] / row["infer_s_per_spectrum"], rel=2e-3
        )
        assert isinstance(row["disturbed"], bool) and isinstance(row["disturbances"], list)
        if row["preset"] == "graf_cpu":  # training steps too, where the model trains
            assert row["train_s_per_step_loaded"] > 0
            assert row["train_slowdown"] == pytest.approx(
                row["train_s_per_step_loaded"] / row["train_s_per_step"], rel=2e-3
            )
        else:
            assert "train_slowdown" not in row or row["train_slowdown"] is None
    md = (Path(cfg.paths.output_dir) / "bench.md").read_text()
    assert "s/spectrum beside a busy process" in md and "s/step beside a busy process" in md
