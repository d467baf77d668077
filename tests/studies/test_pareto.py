"""graf-pareto: fronts, a tiny real sweep (train points, an evaluation point on the base checkpoint, a failing
point that does not stop the others), and resuming without re-running finished points."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir

from graf.app.config import CONF_DIR
from graf.errors import ConfigError
from graf.studies.pareto import pareto_front


def test_pareto_front_keeps_only_undominated_points():
    rows = [
        {"t": 1.0, "val_psnr": 10.0},
        {"t": 2.0, "val_psnr": 12.0},
        {"t": 3.0, "val_psnr": 11.0},
        {"t": 2.0, "val_psnr": 12.0},
        {"t": None, "val_psnr": 30.0},
        {"t": 0.5, "val_psnr": 9.0},
    ]
    assert pareto_front(rows, "t") == {0, 1, 3, 5}  # 2 is slower and worse than 1; 4 has no time


def test_a_reference_method_is_tabled_but_left_out_of_the_fronts(tmp_path):
    """RF-GS faster and better than every GRaF setting would otherwise be the whole front; as a reference knob it
    keeps its row and GRaF's own settings are ranked among themselves."""
    from graf.studies.pareto import collect

    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("pareto", overrides=["only_scenes=[rfid_s23_sparse]", "only_points=[base,voxel_4,rf_gs]"])
    assert list(cfg.reference_knobs) == ["method"]
    figures = {"base": (40.0, 0.13, 15.9), "voxel_4": (27.0, 0.10, 15.9), "rf_gs": (9.0, 0.01, 21.9)}
    for point, (fit_s, infer_s, val) in figures.items():
        folder = tmp_path / "rfid_s23_sparse" / point
        folder.mkdir(parents=True)
        record = {
            "timing": {"fit_s": fit_s, "fit_s_per_step": fit_s / 300, "test_s_per_spectrum": infer_s},
            "metrics": {"val/psnr": val, "test/psnr": val},
        }
        (folder / "results.json").write_text(json.dumps(record))
    rows = {r["point"]: r for r in collect(tmp_path, cfg)}
    assert set(rows) == {"base", "voxel_4", "rf_gs"}
    assert not rows["rf_gs"]["front_infer"] and not rows["rf_gs"]["front_train"]
    assert rows["voxel_4"]["front_infer"] and rows["voxel_4"]["front_train"]  # as good as base, faster
    assert not rows["base"]["front_infer"] and not rows["base"]["front_train"]
    cfg.reference_knobs = []
    rows = {r["point"]: r for r in collect(tmp_path, cfg)}
    assert rows["rf_gs"]["front_infer"] and not rows["voxel_4"]["front_infer"]  # ranked, it dominates
    cfg.reference_knobs = ["methd"]  # a misspelt knob would leave everything in the fronts: it stops instead
    with pytest.raises(ConfigError, match=r"reference_knobs: \['methd'\] is the knob of no point"):
        collect(tmp_path, cfg)


@pytest.mark.parametrize(
    "override, says",
    [
        # a string was split into letters: no knob was a reference (reference_knobs=method), or a traceback
        ("reference_knobs=method", "reference_knobs=method: must be a list of knobs, such as [method]"),
        ("only_points=base", "only_points=base: must be a list of points, such as [base]"),
        ("only_points=[base,voxl_4]", "only_points: ['voxl_4'] is no point of the config (points: ["),
        ("only_scenes=[rfid_s23]", "only_scenes: ['rfid_s23'] is no scene of the config (scenes: ['"),
        ("only_scenes=[base]", "only_scenes: ['base'] is no scene"),  # a point's name is no scene either
        ("threads=0", "threads=0: must be a whole number >= 1 or null"),
    ],
)
def test_a_wrong_setting_stops_graf_pareto_before_any_run_with_one_line(tmp_path, monkeypatch, override, says):
    from graf.studies import pareto

    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("pareto", overrides=[override, f"out={tmp_path / 'out'}", f"paths.output_dir={tmp_path}"])
    monkeypatch.setattr(pareto, "run_command", lambda *a, **k: pytest.fail("a run started"))
    with pytest.raises(ConfigError) as info:
        pareto.sweep(cfg)
    assert str(info.value).startswith(says) and "\n" not in str(info.value)
    assert not (tmp_path / "out").exists()
    if override.startswith("only_points=[base,"):  # every known point is listed
        assert all(p in str(info.value) for p in [*cfg.points, *cfg.eval_points])


def test_config_has_five_knobs_on_two_scenes():
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("pareto")
    knobs = {p.knob for p in cfg.points.values()} | {p.knob for p in cfg.eval_points.values()}
    assert len(knobs - {"base"}) >= 5 and len(cfg.scenes) >= 2


@pytest.mark.slow  # 91 s on the 2-core CI machine: the default run must stay under 15 min
def test_tiny_sweep_runs_records_failures_and_resumes(tmp_path):
    out = tmp_path / "sweep"
    tiny = [
        "trainer.max_steps=2",
        "model.decay_steps=2",
        "logger=none",
        "plot_count=0",
        "model.max_samples=4",
        "model.rays_per_step=64",
        "data.batch_size=2",
        "data.test_subset=4",
        "baselines={}",
        "callbacks.model_checkpoint.every_n_train_steps=2",
    ]
    q = lambda items: "[" + ",".join(f"'{i}'" for i in items) + "]"  # noqa: E731 (quoted: values hold '=')
    args = [
        sys.executable,
        "-m",
        "graf.cli.studies.pareto",
        f"out={out}",
        f"hydra.run.dir={tmp_path / 'h'}",
        "threads=1",
        "only_scenes=[rfid_s23_sparse]",
        "only_points=[base,voxel_2,broken,L_test_3]",
        "base=" + q(tiny),
        "+points.broken={knob: broken, value: x, overrides: " + q(["model.voxel_wavelengths=-1"]) + "}",
    ]
    p = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    r = json.loads((out / "results.json").read_text())
    points = {row["point"]: row for row in r["rows"]}
    assert set(points) == {"base", "voxel_2", "L_test_3"}
    assert [f["point"] for f in r["failed"]] == ["broken"] and "voxel_wavelengths" in r["failed"][0]["log"]
    for row in points.values():
        assert row["infer_s_per_spectrum"] > 0 and row["train_s"] > 0 and row["val_psnr"] is not None
    assert points["L_test_3"]["train_s"] == points["base"]["train_s"]  # evaluated on the base checkpoint
    assert any(row["front_infer"] for row in r["rows"]) and (out / "pareto.png").stat().st_size > 0
    assert (out / "pareto.md").read_text().count("| rfid_s23_sparse |") == 3
    # resuming: finished points are skipped (their results are not rewritten)
    before = (out / "rfid_s23_sparse" / "base" / "results.json").stat().st_mtime_ns
    p = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0 and (out / "rfid_s23_sparse" / "base" / "results.json").stat().st_mtime_ns == before
