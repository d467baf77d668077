"""A study end to end, as a user runs it: one Hydra multirun (base model trained first, zero-shot jobs of
it), resumed after an interruption without recomputing finished jobs, with graf-report's tables at the end;
and user errors that end a command with their message alone."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

EXE = Path(sys.executable).parent


def _run(args: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    e = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    e.update({"OMP_NUM_THREADS": "1", **(env or {})})
    return subprocess.run([str(EXE / args[0]), *args[1:]], cwd=cwd, capture_output=True, text=True, timeout=900, env=e)


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_a_study_multirun_trains_its_base_once_resumes_and_reports(small_room_root, tmp_path):
    sweep = tmp_path / "nc"
    cmd = [
        "graf-train",
        "experiment=neighbor_count",
        "model=knn_dl",
        "scene=small_room",
        "eval_scene=same",
        "neighbors.L=2,4",
        "study_steps=2",
        "study_size=quick",
        "sim_num_tx=24",
        f"data_root={small_room_root}",
        f"hydra.sweep.dir={sweep}",
    ]
    p = _run(cmd, tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    jobs = {int(d.name.split("neighbors.L=")[1].split(",")[0]): d for d in sweep.iterdir() if "neighbors.L=" in d.name}
    assert sorted(jobs) == [2, 4]
    results = {L: json.loads((d / "results.json").read_text()) for L, d in jobs.items()}
    base = sweep / "base" / "knn_dl_small_room_seed0"
    assert json.loads((base / "results.json").read_text())["global_step"] == 2
    for L, r in results.items():
        assert r["config"]["neighbors"]["L"] == L and r["finetune"]["mode"] == "zero-shot"
        assert r["finetune"]["base_steps"] == 2 and r["global_step"] == 0
        assert (jobs[L] / "samples" / "small_room__knn-dl.npz").is_file()
    report = json.loads((sweep / "report.json").read_text())
    for L, r in results.items():  # the report's curve holds the jobs' own figures
        assert report["vs_L"]["knn-dl"][str(L)]["PSNR"] == pytest.approx(r["metrics"]["test/psnr"])
        assert report["vs_L"]["knn"][str(L)]["PSNR"] == pytest.approx(r["baselines"]["knn"]["metrics"]["test/psnr"])
    assert "vs_L.png" in report["figures"] and (sweep / "report.md").is_file()

    # interrupted: the L=4 job did not finish; the same command runs it alone
    stamps = {L: (d / "results.json").stat().st_mtime_ns for L, d in jobs.items()}
    base_stamp = (base / "results.json").stat().st_mtime_ns
    (jobs[4] / "results.json").unlink()
    p = _run(cmd, tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    assert (jobs[2] / "results.json").stat().st_mtime_ns == stamps[2]  # finished: not run again
    assert (jobs[4] / "results.json").is_file()
    assert (base / "results.json").stat().st_mtime_ns == base_stamp  # the base model is not trained again
    assert "finished before" in p.stderr + p.stdout
    again = json.loads((jobs[4] / "results.json").read_text())
    assert again["metrics"]["test/psnr"] == pytest.approx(results[4]["metrics"]["test/psnr"], abs=1e-5)

    # the base model is not reused for other settings
    p = _run(["study_steps=3" if a == "study_steps=2" else a for a in cmd], tmp_path)
    assert "a base model trained with other settings is there" in p.stderr + p.stdout


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_user_errors_end_with_their_message_alone(tmp_path):
    p = _run(
        [
            "graf-train",
            "scene=nerf2",
            "scene.nerf2.path=/nonexistent/folder",
            "band=2.4ghz",
            f"hydra.run.dir={tmp_path / 'a'}",
        ],
        tmp_path,
    )
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-2] == "error: /nonexistent/folder: scene folder does not exist"
    assert "Traceback" not in p.stderr + p.stdout
    p = _run(
        [
            "graf-train",
            "scene=nerf2",
            "scene.nerf2.path=/nonexistent/folder",
            "band=2.4ghz",
            f"hydra.run.dir={tmp_path / 'b'}",
        ],
        tmp_path,
        env={"HYDRA_FULL_ERROR": "1"},
    )
    assert p.returncode != 0 and "Traceback" in p.stderr
    p = _run(["graf-train", "finetune=f20", f"hydra.run.dir={tmp_path / 'c'}"], tmp_path)
    assert p.returncode == 2 and "finetune=f20 fine-tunes a checkpoint: set finetune.init_from=CKPT" in p.stderr
    p = _run(["graf-train", "scene=[rfid_s23,no_such_scene]", f"hydra.run.dir={tmp_path / 'd'}"], tmp_path)
    assert p.returncode == 2 and "scene=no_such_scene: no such option of 'scene'" in p.stderr
    assert "Traceback" not in p.stderr


def test_study_jobs_outside_the_design_are_skipped_with_the_reason(compose_cfg):
    from graf.run.train import skip_reason

    def reason(*overrides):
        return skip_reason(compose_cfg("train", overrides))

    assert reason("same_family_only=true", "scene=conference_v1", "eval_scene=[office_v2]").startswith(
        "same_family_only: test scenes of family office, training scenes of conference"
    )
    assert reason("same_family_only=true", "scene=conference_v1", "eval_scene=[conference_v2]") is None
    # NeRF2, a per-scene model, is trained with seed 0 only in the studies' three-seed sweeps
    assert reason("experiment=cross_scene_matrix", "model=nerf2_study", "seed=1").startswith("single_seed:")
    assert reason("experiment=cross_scene_matrix", "model=nerf2_study", "seed=0") is None
    assert reason("experiment=cross_scene_matrix", "model=knn_dl", "seed=2") is None
    assert reason("experiment=cross_scene_matrix", "study_size=quick", "model=nerf2_study", "seed=1") is None
    assert reason("same_family_only=false", "scene=conference_v1", "eval_scene=[office_v2]") is None
    # base.band=scene: for a simulated scene the same job as with the run's band; measured data keeps its band
    assert "the same job as the one with the run's band" in reason(
        "experiment=unseen_layouts", "scene=bedroom", "finetune.base.band=scene"
    )
    assert reason("experiment=unseen_layouts", "scene=rfid_s23", "finetune.base.band=scene") is None


@pytest.mark.parametrize("study", ["bands", "cross_scene_matrix", "density", "neighbor_count", "unseen_layouts"])
def test_a_study_optimises_nothing_so_its_jobs_return_no_sweep_value(compose_cfg, study, caplog):
    from graf.run.evaluation import sweep_value

    cfg = compose_cfg("train", (f"experiment={study}",))
    assert cfg.validate is False and cfg.optimized_metric is None
    with caplog.at_level("WARNING", logger="graf"):  # no "val/psnr is nan; reporting the worst value" per job
        assert sweep_value(cfg, {"val/psnr": None, "test/psnr": 20.0}) == 0.0
    assert not caplog.records
    # a search composed with a study keeps its own metric (hparams_search comes after experiment)
    assert compose_cfg("train", (f"experiment={study}", "hparams_search=neighbor_count")).optimized_metric
