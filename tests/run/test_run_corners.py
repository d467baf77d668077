"""A run's corners: Ctrl+C during graf-train, a new run in a finished run's folder, baselines={} in the recorded
config, and KNN-DL's rank scale taken from the run's neighbor selector."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import open_dict

from graf.app.config import CONF_DIR
from graf.run import train as train_module
from graf.run.build import build
from graf.run.train import train
from graf.run.writer import REPLACED_RESULTS

KNN_DL = ("model=knn_dl", "data.batch_size=2", "data.test_subset=2", "plot_count=0")


def test_ctrl_c_during_training_says_where_it_stopped_and_how_to_resume(tmp_path):
    exe = str(Path(sys.executable).parent / "graf-train")
    out = tmp_path / "run"
    args = [*KNN_DL, "trainer.max_steps=100000", "trainer.accelerator=cpu", "logger=none", "baselines={}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    args += ["callbacks.model_checkpoint.every_n_train_steps=2", f"hydra.run.dir={out}"]
    p = subprocess.Popen(
        [exe, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    ckpt = out / "checkpoints" / "last.ckpt"
    deadline = time.time() + 120
    while time.time() < deadline and not ckpt.exists() and p.poll() is None:
        time.sleep(0.05)
    assert ckpt.exists(), "training never started"
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == 130, stderr[-3000:]
    step = torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"]  # saved at the interrupt
    assert f"training stopped at step {step} of 100000 (epoch 0)" in stderr
    assert f"output folder: {out}" in stderr
    assert f"resume with: {shlex.join(['graf-train', *args, f'ckpt_path={ckpt}'])}\n" in stderr
    assert not (out / "results.json").exists()


def test_a_new_run_moves_a_finished_runs_files_aside_and_a_resume_keeps_them(compose_cfg, tmp_path, monkeypatch):
    out = tmp_path / "out"
    cfg = compose_cfg("train", (*KNN_DL, "trainer.max_steps=2", "save_predictions=true"))
    train(cfg)
    first = json.loads((out / "results.json").read_text())
    # a resume of the run in this folder keeps its files (and its results.json is replaced when it finishes)
    train(compose_cfg("train", (*KNN_DL, "trainer.max_steps=3", f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}")))
    assert not list(out.glob("replaced_*")) and json.loads((out / "results.json").read_text())["global_step"] == 3

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "build", interrupted)  # a new run, stopped before it wrote anything
    with pytest.raises(KeyboardInterrupt):
        train(cfg)
    assert not (out / "results.json").exists()  # the folder no longer looks finished
    (aside,) = out.glob("replaced_*")
    old = json.loads((aside / REPLACED_RESULTS).read_text())
    assert old["global_step"] == 3 and old["config"]["seed"] == first["config"]["seed"]
    assert (aside / "predictions.npz").is_file() and (aside / "checkpoints" / "last.ckpt").is_file()


def test_baselines_off_on_the_command_line_is_the_recorded_config(tmp_path):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "train",
            overrides=["model=knn", "baselines={}", f"paths.output_dir={tmp_path}", "logger=none", "plot_count=0"],
            return_hydra_config=True,
        )
    GlobalHydra.instance().clear()
    assert list(cfg.baselines) == ["knn"]  # Hydra merged {} into the composed group: a no-op
    HydraConfig.instance().set_config(cfg)
    try:
        with open_dict(cfg):
            del cfg["hydra"]
        _, run = train(cfg)
    finally:
        HydraConfig.instance().cfg = None
    recorded = json.loads((tmp_path / "results.json").read_text())
    assert recorded["config"]["baselines"] == {} and "baselines" not in recorded
    assert run.record.config["baselines"] == {}


@pytest.mark.parametrize(("neighbors", "rank"), [((), 10), (("neighbors.L=16", "neighbors.L_train=[3,16]"), 16)])
def test_knn_dl_rank_scale_is_the_largest_l_of_the_runs_neighbors(compose_cfg, neighbors, rank):
    cfg = compose_cfg("train", ("model=knn_dl", *neighbors))
    assert cfg.model.max_rank is None
    built = build(cfg)
    assert built.neighbors.max_L == rank
    assert built.model.hparams.max_rank == rank and built.cfg.model.max_rank == rank  # the config recorded


def test_a_sigterm_stops_a_command_in_every_stage_but_training_at_once_saying_what_was_kept():
    """SIGTERM (issue 68): outside training the command stops at once with the stage and what was kept (exit code
    143, as a pre-empted training); in training the handler leaves it to Lightning, which stops after the step in
    progress and saves it."""
    from graf.errors import is_preempted
    from graf.interrupts import Terminated, _on_sigterm, stage

    with stage("testing", lambda: "training had finished at step 3"):
        with pytest.raises(Terminated, match="stopped by SIGTERM during testing; training had finished at step 3") as e:
            _on_sigterm(signal.SIGTERM, None)
    assert is_preempted(e.value) and e.value.said_kept
    with stage("set-up"):  # no stage says what was kept: the command adds its output folder
        with pytest.raises(Terminated) as e:
            _on_sigterm(signal.SIGTERM, None)
    assert str(e.value) == "stopped by SIGTERM during set-up" and not e.value.said_kept
    with stage("training", lambda: "results.json was not written"):
        assert _on_sigterm(signal.SIGTERM, None) is None  # Lightning's connector stops the fit at the step's end


@pytest.mark.slow  # about 20 s: a real graf-train, signalled while it tests
def test_a_sigterm_while_graf_train_tests_stops_it_with_143_and_the_way_to_test_the_checkpoint(tmp_path):
    exe = str(Path(sys.executable).parent / "graf-train")
    out = tmp_path / "run"
    args = ["experiment=graf_rfid_s23", "trainer.max_steps=3", "model.rays_per_step=64", "data.batch_size=2",
            "logger=none", "plot_count=0", f"hydra.run.dir={out}"]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    p = subprocess.Popen([exe, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    ckpt = out / "checkpoints" / "last.ckpt"
    deadline = time.time() + 300
    while time.time() < deadline and not ckpt.exists() and p.poll() is None:  # written when the 3 steps are done
        time.sleep(0.05)
    assert ckpt.exists(), "training never finished"
    time.sleep(1.0)  # into validation and testing
    p.send_signal(signal.SIGTERM)
    _, stderr = p.communicate(timeout=120)
    assert p.returncode == 143, stderr[-3000:]
    assert "stopped by SIGTERM during testing; training had finished at step 3" in stderr
    assert f"ckpt_path={ckpt}" in stderr and not (out / "results.json").exists()
    assert "Traceback" not in stderr
