"""graf-curves (issue 22, point 4): one resumable trajectory per method, validated at each step, never tested."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


@pytest.mark.slow  # 75 s on the 2-core CI machine: the default run must stay under 15 min
def test_curves_run_resume_and_validate_only(tmp_path, make_scene):
    folder = make_scene(n=24)
    out = tmp_path / "curves"
    q = lambda *o: "[" + ",".join(f"'{x}'" for x in o) + "]"  # noqa: E731  (a Hydra list of overrides)
    regime = q(
        "scene=nerf2",
        f"scene.nerf2.path={folder}",
        "band=2.4ghz",
        "data.batch_size=2",
        "data.val_fraction=0.2",
        "data.test_subset=2",
    )
    small = ("model.rays_per_step=32", "model.max_samples=4", "model.encoder_widths=[4,8,8,8]")
    args = [
        sys.executable,
        "-m",
        "graf.cli.studies.curves",
        f"out={out}",
        "threads=1",
        "steps=[1,2]",
        f"+regimes={{tiny: {{max_steps: 3, overrides: {regime}}}}}",
        "only_regimes=[tiny]",
        f"methods.pooled.overrides={q('model=graf_cpu', *small)}",
        f"methods.ray_knn.overrides={q('model=graf_cpu', 'model/features=ray_knn', *small)}",
        "only_methods=[pooled,ray_knn]",
        f"hydra.run.dir={tmp_path / 'h'}",
    ]
    p = subprocess.run([*args, "until=2"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert [(r["method"], r["step"]) for r in res["rows"]] == [
        ("pooled", 1),
        ("pooled", 2),
        ("ray_knn", 1),
        ("ray_knn", 2),
    ]
    assert all(r["val_psnr"] is not None and r["val_reliance_db"] is not None for r in res["rows"])
    assert {r["device"] for r in res["rows"]} == {"cpu"}  # where each point trained (a GPU point names its card)
    assert res["knn"]["tiny"]["val/psnr"] is not None and not res["failed"]
    step2 = json.loads((out / "tiny" / "ray_knn" / "step_2" / "results.json").read_text())
    assert step2["resumed"]["global_step"] == 1 and step2["training"]["steps_trained"] == 1  # one trajectory
    assert step2["metrics"]["test/psnr"] is None  # never tested
    first = (out / "tiny" / "pooled" / "step_1" / "results.json").stat().st_mtime
    p = subprocess.run(args, capture_output=True, text=True, timeout=600)  # again, to the budget: resumes
    assert p.returncode == 0, p.stderr[-3000:]
    assert (out / "tiny" / "pooled" / "step_1" / "results.json").stat().st_mtime == first  # not run again
    res = json.loads((out / "results.json").read_text())
    assert [r["step"] for r in res["rows"] if r["method"] == "pooled"] == [1, 2, 3]
    assert (out / "curves.png").is_file() and "knn (line)" in (out / "curves.md").read_text()
    kept = [
        p.name for p in sorted((out / "tiny" / "pooled").glob("step_*")) if (p / "checkpoints" / "last.ckpt").is_file()
    ]
    assert kept == ["step_3"]  # (each point's checkpoints/ links under checkpoint_root: rglob would not follow it)
    # a run of a subset (one method, an earlier until) trains nothing and keeps every other published row
    subset = [a for a in args if not a.startswith("only_methods=")] + ["only_methods=[pooled]", "until=1"]
    p = subprocess.run(subset, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    again = json.loads((out / "results.json").read_text())
    assert again["rows"] == res["rows"] and "| ray_knn | 3 |" in (out / "curves.md").read_text()


def test_a_preempted_point_resumes_from_its_own_checkpoint_and_its_seconds_count(tmp_path):
    from graf.studies.curves import PREEMPTED_RUNS, preempted_runs, resume_from

    prev, folder = tmp_path / "step_1000", tmp_path / "step_10000"
    (folder / "checkpoints").mkdir(parents=True)
    assert resume_from(folder, None) is None  # a curve's first point starts from scratch
    assert resume_from(folder, prev) == prev / "checkpoints" / "last.ckpt"
    ckpt = folder / "checkpoints" / "last.ckpt"
    ckpt.write_bytes(b"state at step 4200")
    (folder / "preempted.json").write_text(json.dumps({"global_step": 4200, "checkpoint": str(ckpt), "fit_s": 5000.0}))
    assert resume_from(folder, prev) == ckpt  # not the previous point's: 3,200 steps are not lost
    assert not (folder / "preempted.json").exists() and [r["fit_s"] for r in preempted_runs(folder)] == [5000.0]
    (folder / "preempted.json").write_text(json.dumps({"global_step": 4300, "checkpoint": str(folder / "gone.ckpt")}))
    assert resume_from(folder, prev) == prev / "checkpoints" / "last.ckpt"  # nothing saved: start the point again
    assert not (folder / "preempted.json").exists() and len(json.loads((folder / PREEMPTED_RUNS).read_text())) == 1


def test_a_preempted_point_moved_to_another_folder_resumes_from_its_own_checkpoint(tmp_path):
    """A curve run in one folder and published, stopped, into sweeps/: preempted.json names the old path."""
    from graf.studies.curves import preempted_runs, resume_from

    prev, folder = tmp_path / "published" / "step_1000", tmp_path / "published" / "step_3000"
    (folder / "checkpoints").mkdir(parents=True)
    ckpt = folder / "checkpoints" / "last.ckpt"
    ckpt.write_bytes(b"state at step 2100")
    old = tmp_path / "elsewhere" / "step_3000" / "checkpoints" / "last.ckpt"  # where it was saved; gone now
    (folder / "preempted.json").write_text(json.dumps({"global_step": 2100, "checkpoint": str(old), "fit_s": 1700.0}))
    assert resume_from(folder, prev) == ckpt
    assert [r["checkpoint"] for r in preempted_runs(folder)] == [str(ckpt)]


def test_a_killed_point_resumes_from_its_periodic_checkpoint_and_its_saved_seconds_count(tmp_path):
    """A run killed outright (SIGKILL: no preempted.json) left a periodic last.ckpt: the point resumes from it, not
    from the previous point, and the seconds its saved steps cost (AttemptClock's record) count in fit_s."""
    import torch

    from graf.studies.curves import preempted_runs, resume_from

    prev, folder = tmp_path / "step_3000", tmp_path / "step_10000"
    (folder / "checkpoints").mkdir(parents=True)
    ckpt = folder / "checkpoints" / "last.ckpt"
    torch.save({"global_step": 4500, "graf_attempt": {"start_step": 3000, "global_step": 4500, "fit_s": 2250.5}}, ckpt)
    assert resume_from(folder, prev) == ckpt
    [record] = preempted_runs(folder)
    assert (
        record["killed"]
        and record["global_step"] == 4500
        and record["start_step"] == 3000
        and record["fit_s"] == 2250.5
    )
    # killed again later, from a checkpoint written before AttemptClock existed: resumed, its seconds unknown (None)
    torch.save({"global_step": 5000}, ckpt)
    assert resume_from(folder, prev) == ckpt
    assert [r["fit_s"] for r in preempted_runs(folder)] == [2250.5, None]
    # a checkpoint already on record (a pre-emption's, resumed and then killed before its next save): resumed
    # from again, its seconds not counted twice
    torch.save({"global_step": 5000, "graf_attempt": {"start_step": 4500, "global_step": 5000, "fit_s": 300.0}}, ckpt)
    assert resume_from(folder, prev) == ckpt and len(preempted_runs(folder)) == 2
    # a finished point is never resumed; an unreadable checkpoint starts the point again from the previous one,
    # moved aside (graf-train refuses a new run beside an interrupted run's checkpoint)
    ckpt.write_bytes(b"truncated")
    assert resume_from(folder, prev) == prev / "checkpoints" / "last.ckpt"
    assert (folder / "checkpoints.unreadable" / "last.ckpt").read_bytes() == b"truncated" and not ckpt.exists()
    (folder / "checkpoints").mkdir()
    (folder / "results.json").write_text("{}")
    torch.save({"global_step": 5000}, ckpt)
    assert resume_from(folder, prev) == prev / "checkpoints" / "last.ckpt"
    assert len(preempted_runs(folder)) == 2


def test_attempt_clock_writes_its_attempt_into_each_checkpoint():
    from types import SimpleNamespace

    from graf.callbacks import AttemptClock

    clock, trainer = AttemptClock(), SimpleNamespace(global_step=3000)
    ckpt: dict = {}
    clock.on_save_checkpoint(trainer, None, ckpt)
    assert "graf_attempt" not in ckpt  # not training (a checkpoint saved outside fit): no attempt to record
    clock.on_train_start(trainer, None)
    trainer.global_step = 3500
    clock.on_save_checkpoint(trainer, None, ckpt)
    a = ckpt["graf_attempt"]
    assert a["start_step"] == 3000 and a["global_step"] == 3500 and a["fit_s"] >= 0.0


def test_a_checkpoint_interval_under_one_step_stops_with_one_line(tmp_path):
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "graf.cli.studies.curves",
            f"out={tmp_path}",
            "checkpoint_every=0",
            f"hydra.run.dir={tmp_path / 'h'}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2 and "checkpoint_every=0: must be a whole number >= 1" in p.stderr
    assert "Traceback" not in p.stderr


def _curves_cfg(*overrides: str):
    """conf/curves.yaml as graf-curves composes it, with these overrides."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from graf.app.config import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="curves", overrides=list(overrides))
    GlobalHydra.instance().clear()
    return cfg


@pytest.mark.parametrize(
    "override, says",
    [
        ("until=-1", "until=-1: must be a whole number >= 1 or null"),  # it ran nothing and said nothing
        ("until=2.5", "until=2.5: must be a whole number >= 1 or null"),
        ("threads=0", "threads=0: must be a whole number >= 1 or null"),
        ("steps=abc", "steps=abc: must be a list of step counts, such as [100,1000]"),  # a traceback
        ("steps=[100,abc]", "steps[1]=abc: must be a whole number >= 1"),
        ("only_regimes=main_job", "only_regimes=main_job: must be a list, such as [main_job]"),
        ("only_methods=[nope]", "only_methods: unknown keys ['nope'] (known: "),
        (
            "regimes.cross_family_val_30k.continues=nowhere",
            "curves.yaml: regimes.cross_family_val_30k.continues: 'nowhere' is not another regime of the file",
        ),
    ],
)
def test_a_wrong_setting_stops_graf_curves_before_any_run_with_one_line(override, says):
    from graf.errors import ConfigError
    from graf.studies.curves_settings import check_settings

    with pytest.raises(ConfigError) as info:
        check_settings(_curves_cfg(override))
    assert str(info.value).startswith(says) and "\n" not in str(info.value)


def test_the_shipped_curves_config_passes_its_checks_and_graf_curves_checks_first(tmp_path, monkeypatch):
    from graf.errors import ConfigError
    from graf.studies import curves as C
    from graf.studies.curves_settings import check_settings

    check_settings(_curves_cfg())
    check_settings(_curves_cfg("until=1000", "threads=2", "only_regimes=[main_job]"))
    monkeypatch.setattr(C, "run_command", lambda *a, **k: pytest.fail("a run started"))
    with pytest.raises(ConfigError, match="until=-1"):
        C.curves(_curves_cfg("until=-1", f"out={tmp_path / 'out'}", f"paths.output_dir={tmp_path}"))
    assert not (tmp_path / "out").exists()


def test_a_points_device_is_short_in_the_table():
    from graf.run.evaluation import short_device

    assert short_device("cuda:0 (NVIDIA H200)") == "NVIDIA H200"
    assert short_device("cpu") == "cpu" and short_device(None) is None


def test_a_point_resumed_on_another_device_names_each_attempts_device_in_order(tmp_path):
    """A point begun on a lent GPU and finished on the CPU: the table says both, not only the last."""
    from omegaconf import OmegaConf

    from graf.studies.curves import PREEMPTED_RUNS, attempt_devices, collect

    gpu, old = {"device": "cuda:0 (NVIDIA H200)", "fit_s": 450.0}, {"fit_s": 2000.0}  # old: a record with no device
    assert attempt_devices([gpu], "cpu") == "NVIDIA H200 + cpu"
    assert attempt_devices([old, {"device": "cpu"}], "cpu") == "cpu"  # each device once; unknown ones left out
    assert attempt_devices([], None) is None
    cfg = OmegaConf.create({"steps": [10], "regimes": {"r": {"max_steps": 10}}, "methods": {"m": {}}})
    folder = tmp_path / "r" / "m" / "step_10"
    folder.mkdir(parents=True)
    (folder / PREEMPTED_RUNS).write_text(json.dumps([gpu]))
    metrics = {"val/psnr": 20.0, "val/ssim": 0.8, "val/lpips": 0.2}
    record = {"device": "cpu", "global_step": 10, "timing": {"fit_s": 100.0}, "metrics": metrics}
    (folder / "results.json").write_text(json.dumps(record))
    rows, _ = collect(tmp_path, cfg)
    assert [(r["device"], r["fit_s"]) for r in rows] == [("NVIDIA H200 + cpu", 550.0)]


def test_nerf2_has_a_curve_only_in_the_single_scene_regime():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from graf.app.config import CONF_DIR
    from graf.studies.curves import regime_methods

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("curves")
    GlobalHydra.instance().clear()
    assert "nerf2" in regime_methods(cfg, "rfid_sparse")
    for zero_shot in ("cross_family", "cross_family_paper"):  # validated on layouts it never saw: no curve
        assert "nerf2" not in regime_methods(cfg, zero_shot)
        assert {"pooled", "ray", "ray_knn", "ray_weights", "knn_dl"} <= set(regime_methods(cfg, zero_shot))
    assert regime_methods(cfg, "paper_within") == [
        "rf_gs",
        "rf_gs_knn",
    ]  # the regime lists its methods: a per-scene one's curve
    cfg.only_methods = ["nerf2", "ray"]
    assert regime_methods(cfg, "cross_family_paper") == ["ray"]
    # the 30,000-step budget of regime (d): the same runs and validation layouts, its own schedule's length, and only
    # the curves the rule sends on; a GRaF mode keeps its 4-D positions there
    long, val = cfg.regimes.cross_family_val_30k, cfg.regimes.cross_family_val
    assert list(long.overrides) == list(val.overrides) and int(long.max_steps) == 30000
    assert "eval_scene=[conference_v4,office_v4]" in list(long.overrides)
    cfg.only_methods = None
    assert regime_methods(cfg, "cross_family_val_30k") == list(long.methods)
    assert all("model.use_scene_index=true" in cfg.methods[m].regimes.cross_family_val_30k for m in long.methods)


def test_a_regime_may_have_its_own_evaluation_points():
    from omegaconf import OmegaConf

    from graf.studies.curves import points

    cfg = OmegaConf.create({"steps": [100, 300, 1000, 3000], "until": 1000})
    assert points(cfg, OmegaConf.create({"max_steps": 3000}), until=False) == [100, 300, 1000, 3000]
    own = OmegaConf.create({"max_steps": 10000, "steps": [1000, 3000]})
    assert points(cfg, own, until=False) == [1000, 3000, 10000]  # the budget is always a point
    assert points(cfg, own) == [1000]


def test_a_regime_of_own_runs_trains_each_point_from_scratch_over_its_own_steps(tmp_path, monkeypatch):
    """``each_point: own_run`` (issue 68): every point is a run of its own, its schedule over its own steps (the
    recipe a study with that budget runs), nothing resumed from the point before; its seconds are its own, and a
    missing or failed point hides no later one."""
    from omegaconf import OmegaConf

    from graf.errors import ConfigError
    from graf.studies import curves as C

    cfg = OmegaConf.create(
        {
            "steps": [10, 30],
            "checkpoint_every": 500,
            "regimes": {"r": {"max_steps": 100, "each_point": "own_run", "overrides": []}},
            "methods": {"m": {"overrides": [], "schedule": "model.decay_steps"}},
        }
    )
    cmds = []

    def fake_point(cmd, folder, env, cfg_, out, failed):
        cmds.append(cmd)
        step = int(next(a for a in cmd if a.startswith("trainer.max_steps=")).split("=")[1])
        if step == 30:
            return False, "boom"  # a failed point: the next one still runs
        folder.mkdir(parents=True, exist_ok=True)
        metrics = {"val/psnr": float(step), "val/ssim": 0.5, "val/lpips": 0.3}
        record = {"global_step": step, "timing": {"fit_s": float(step)}, "metrics": metrics}
        (folder / "results.json").write_text(json.dumps(record))
        return True, ""

    monkeypatch.setattr(C, "_run_point", fake_point)
    failed = C._run_curve(cfg, tmp_path, {}, "r", "m", [], [])
    schedules = [next(a for a in c if a.startswith("model.decay_steps=")) for c in cmds]
    assert schedules == ["model.decay_steps=10", "model.decay_steps=30", "model.decay_steps=100"]
    assert not any(a.startswith("ckpt_path=") for c in cmds for a in c)  # nothing resumed
    assert [f["step"] for f in failed] == [30]
    rows, _ = C.collect(tmp_path, cfg)
    assert [(r["step"], r["fit_s"]) for r in rows] == [(10, 10.0), (100, 100.0)]  # its own seconds, not a sum
    cfg.regimes.r.each_point = "resume"  # the trajectory's table stops at its first missing point
    assert [r["step"] for r in C.collect(tmp_path, cfg)[0]] == [10]
    cfg.regimes.r.each_point = "own-run"
    with pytest.raises(ConfigError, match="regimes.r.each_point: 'own-run' is not one of resume, own_run"):
        C.collect(tmp_path, cfg)


def test_the_studies_and_the_main_job_have_curves_of_their_own_recipe():
    """The regimes the studies' budgets and the main job's choice are read from train each point as the study or the
    main job does (issue 68): own runs, the same experiment, batch and validation carve-out as the matrix's jobs."""
    from omegaconf import OmegaConf

    from graf.app.config import CONF_DIR

    c = OmegaConf.load(CONF_DIR / "curves.yaml")
    m, main = c.regimes.matrix_recipe_val, c.regimes.main_job
    assert m.each_point == main.each_point == "own_run"
    assert {"data.batch_size=4", "data.val_fraction=0.1", "scene=[conference_v1]"} <= set(m.overrides)
    assert "model.use_scene_index=true" in c.methods.ray_weights.regimes.matrix_recipe_val
    assert list(main.overrides) == ["experiment=graf_rfid_s23"] and max(main.steps) == main.max_steps


def test_a_points_checkpoints_live_under_the_checkpoint_root_and_go_with_it(tmp_path):
    """checkpoint_root: a point's checkpoints/ links to a folder outside the record (the point's path mirrored under
    the root); dropping them removes the folder and the link; a point with a folder of its own keeps it."""
    from graf.studies.curves import drop_checkpoints, link_checkpoints

    folder, root = tmp_path / "sweeps" / "r" / "m" / "step_300", tmp_path / "outside"
    link_checkpoints(folder, root)
    link = folder / "checkpoints"
    assert link.is_symlink() and link.resolve().is_relative_to(root.resolve())
    (link / "last.ckpt").write_bytes(b"x")
    target = link.resolve()
    assert (target / "last.ckpt").is_file()
    drop_checkpoints(folder)
    assert not link.exists() and not link.is_symlink() and not target.exists()
    own = tmp_path / "own"
    (own / "checkpoints").mkdir(parents=True)
    link_checkpoints(own, root)  # a folder of its own stays a folder
    assert not (own / "checkpoints").is_symlink()
    link_checkpoints(tmp_path / "inside", None)  # null: nothing linked, the run makes its own folder
    assert not (tmp_path / "inside").exists()
