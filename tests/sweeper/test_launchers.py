"""Sweeps through Hydra's submitit launcher (issue 25, part 2), tested with ``submitit_local`` on this machine (each
job a process of its own, as on a cluster each job is a SLURM job): a 2-job multirun of graf-eval and a 4-trial
Optuna search give the same results as Hydra's basic launcher; the SLURM preset composes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import optuna
import pytest

from tests.sweeper.test_optuna_sweeper import run_app

pytest.importorskip("hydra_plugins.hydra_submitit_launcher")


def _trials(tmp: Path) -> list[tuple[dict, float, str]]:
    study = optuna.load_study(study_name="study", storage=f"sqlite:///{tmp / 'sweep' / 'optuna.db'}")
    return [(t.params, t.value, t.state.name) for t in study.trials]


def _pids(tmp: Path) -> set[str]:
    return {p.name.rsplit("_", 1)[1] for p in (tmp / "marks").glob("started_*")}


@pytest.mark.slow  # a process per trial: about 20 s
def test_a_search_through_submitit_local_equals_the_basic_launchers(tmp_path):
    basic, local = tmp_path / "basic", tmp_path / "submitit"
    basic.mkdir(), local.mkdir()
    r = run_app(basic)
    assert r.returncode == 0, r.stderr[-3000:]
    r = run_app(local, "hydra/launcher=submitit_local")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Submitit 'local' sweep output dir" in r.stdout + r.stderr
    assert _trials(local) == _trials(basic) and len(_trials(basic)) == 4
    assert len(_pids(basic)) == 1 and len(_pids(local)) == 4  # in-process trials, against a process per trial


@pytest.mark.slow  # two graf-eval jobs, twice: about a minute
def test_a_two_job_multirun_through_submitit_local_equals_the_basic_launchers(tmp_path):
    def multirun(out: Path, *extra: str) -> list[dict]:
        p = subprocess.run(
            [sys.executable, "-m", "graf.cli.evaluate", "-m", "model=knn", "neighbors=fixed", "neighbors.L=2,6",
             "logger=none", "plot_count=0", f"hydra.sweep.dir={out}", f"data_root={tmp_path / 'data'}", *extra],
            capture_output=True, text=True, timeout=900,
        )  # fmt: skip
        assert p.returncode == 0, p.stderr[-3000:]
        runs = sorted(out.glob("*/results.json"))
        assert len(runs) == 2, runs
        return [json.loads(f.read_text()) for f in runs]

    basic = multirun(tmp_path / "basic")
    local = multirun(tmp_path / "submitit", "hydra/launcher=submitit_local")
    assert (tmp_path / "submitit" / ".submitit").is_dir()  # the jobs went through submitit
    for b, s in zip(basic, local):
        assert b["config"]["neighbors"] == s["config"]["neighbors"]
        for k in ("test/psnr", "test/ssim", "test/lpips", "test/reliance_db"):
            assert s["metrics"][k] == pytest.approx(b["metrics"][k], abs=1e-6), k
    assert {r["config"]["neighbors"]["L"] for r in basic} == {2, 6}


def test_the_slurm_preset_composes_with_the_cluster_settings():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from graf.app.config import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "train",
            ["hydra/launcher=slurm", "hydra.launcher.partition=gpu", "hydra.launcher.cpus_per_task=4"],
            return_hydra_config=True,
        )
    GlobalHydra.instance().clear()
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert (launcher.partition, launcher.gpus_per_node, launcher.timeout_min) == ("gpu", 1, 240)
    assert launcher.setup == ["export OMP_NUM_THREADS=4 MKL_NUM_THREADS=4"]  # the job's threads follow its CPUs
