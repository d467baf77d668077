"""graf-train with GRaF through the real configs: a short run, and a killed run resumed from its checkpoint."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from graf.models.base import CheckpointError
from graf.run.train import train

FAST = [
    "model.rays_per_step=64",
    "model.max_samples=8",
    "data.batch_size=2",
    "baselines={}",
    "plot_count=1",
    "data.test_subset=2",
    "trainer.enable_progress_bar=false",
]


@pytest.mark.slow  # 88 s in the default run of 2026-12-04 (2 workers): the default tests stay under 5 min
def test_graf_train_two_steps_through_the_real_configs(compose_cfg):
    # the main job's GRaF (graf_cpu_ray_weights: ray_weights), the seed-literal pooled one, and its residual variant
    for extra, method in (
        ((), "graf-ray-weights"),
        (("model=graf_cpu",), "graf"),
        (("model=graf_cpu", "model.residual=true"), "graf-residual"),
    ):
        cfg = compose_cfg("train", ("experiment=graf_rfid_s23", "trainer.max_steps=2", *extra, *FAST))
        metrics, _ = train(cfg)
        r = json.loads((Path(cfg.paths.output_dir) / "results.json").read_text())
        assert r["method"] == method
        assert r["global_step"] == 2 and r["trainable_parameters"] > 100_000
        assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())
        assert (Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt").is_file()


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_killed_training_resumes_from_its_last_checkpoint(tmp_path):
    exe = str(Path(sys.executable).parent / "graf-train")
    args = [
        "experiment=graf_rfid_s23",
        "trainer.max_steps=16",
        "callbacks.model_checkpoint.every_n_train_steps=2",
        "trainer.accelerator=cpu",
        "logger=none",
        *FAST,
    ]
    first = tmp_path / "first"
    p = subprocess.Popen(
        [exe, *args, f"hydra.run.dir={first}"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    ckpt = first / "checkpoints" / "last.ckpt"
    deadline = time.time() + 300
    while time.time() < deadline and not ckpt.exists() and p.poll() is None:
        time.sleep(0.01)
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert ckpt.exists(), "no checkpoint was written before the kill"
    step_at_kill = torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"]
    assert 2 <= step_at_kill < 16 and not (first / "results.json").exists()
    second = tmp_path / "second"
    p = subprocess.run(
        [exe, *args, f"ckpt_path={ckpt}", f"hydra.run.dir={second}"], capture_output=True, text=True, timeout=600
    )
    assert p.returncode == 0, p.stderr[-3000:]
    r = json.loads((second / "results.json").read_text())
    assert r["global_step"] == 16  # continued from the checkpoint to the planned length, not restarted
    resumed = torch.load(second / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert resumed["global_step"] == 16
    # ... and ends with the weights of a run that was never interrupted (same batches, neighbors and rays)
    third = tmp_path / "uninterrupted"
    p = subprocess.run([exe, *args, f"hydra.run.dir={third}"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    whole = torch.load(third / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    assert all(torch.equal(v, whole[k]) for k, v in resumed["state_dict"].items())


@pytest.mark.slow  # 15-25 s: GRaF's two training steps stay in the default set
def test_finetune_starts_from_a_checkpoints_weights_and_rejects_another_architecture(compose_cfg, tmp_path):
    cfg = compose_cfg("train", ("experiment=graf_rfid_s23", "trainer.max_steps=2", *FAST))
    train(cfg)
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    trained = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]

    from hydra.utils import instantiate

    from graf.run.finetune import load_weights

    fresh = instantiate(cfg.model)
    assert not all(torch.equal(fresh.state_dict()[k], v) for k, v in trained.items())
    load_weights(fresh, ckpt)
    assert all(torch.equal(v, trained[k]) for k, v in fresh.state_dict().items())

    cfg2 = compose_cfg(
        "train",
        (
            "experiment=graf_rfid_s23",
            "finetune=f100",
            "finetune.max_steps=1",
            f"finetune.init_from={ckpt}",
            f"paths.output_dir={tmp_path / 'ft'}",
            *FAST,
        ),
    )
    train(cfg2)
    r = json.loads((tmp_path / "ft" / "results.json").read_text())
    assert r["global_step"] == 1  # a fresh schedule, not a resumed one
    other = compose_cfg(
        "train", ("experiment=graf_rfid_s23", "model.d_model=8", "finetune=f100", f"finetune.init_from={ckpt}", *FAST)
    )
    with pytest.raises(ValueError, match="another architecture"):
        train(other)
    missing = compose_cfg(
        "train",
        (
            "experiment=graf_rfid_s23",
            "finetune=f100",
            "finetune.max_steps=1",
            f"finetune.init_from={tmp_path / 'nope.ckpt'}",
            *FAST,
        ),
    )
    with pytest.raises(CheckpointError, match="nope.ckpt: checkpoint file does not exist"):
        train(missing)


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_eval_of_a_checkpoint_applies_inference_settings_and_refuses_the_rest(compose_cfg, tmp_path):
    from graf.run.evaluate import evaluate

    cfg = compose_cfg(
        "train", ("experiment=graf_rfid_s23", "trainer.max_steps=1", "model=graf_cpu", "model.residual=true", *FAST)
    )
    train(cfg)
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    common = ("data.test_subset=2", "plot_count=0")

    def run(*overrides, out="e", path=ckpt):
        ecfg = compose_cfg("eval", (f"ckpt_path={path}", *common, *overrides, f"paths.output_dir={tmp_path / out}"))
        evaluate(ecfg, overrides=list(overrides))
        return json.loads((tmp_path / out / "results.json").read_text())

    # an inference setting is applied; the rest of the model is the checkpoint's, not the preset's
    r = run("model=graf_cpu", "model.chunk_rays=512", "model.residual=true")
    assert r["method"] == "graf-residual" and r["config"]["model"]["residual"] is True
    assert r["config"]["model"]["chunk_rays"] == 512 and r["checkpoint"]["applied_overrides"] == {"chunk_rays": 512}
    assert r["config"]["model"]["max_samples"] == 8 and r["checkpoint"]["global_step"] == 1
    assert r["ray_sampling"]["rfid_s23"]["capped"] is True  # max_samples=8 < the 17 wavelengths of rfid_s23
    assert all(np.isfinite(v) for v in r["metrics"].values()) and "val/psnr" in r["metrics"]
    # without model=... the class comes from the checkpoint (the default model=knn is not used)
    assert run(out="plain")["method"] == "graf-residual"
    # a training setting would describe a model that did not run: refused
    with pytest.raises(
        CheckpointError,
        match=r"model.lr=0.1 cannot change the trained checkpoint .*last.ckpt "
        r"\(it was trained with lr=0.0005\); only inference settings may be "
        r"overridden at evaluation: model.chunk_rays",
    ):
        run("model=graf_cpu", "model.lr=0.1")
    with pytest.raises(
        CheckpointError,
        match=r"holds a graf.models.graf.module.GRaFModule checkpoint, but "
        r"model=knn_dl is graf.models.knn_dl.KNNDLModule",
    ):
        run("model=knn_dl")
    # a checkpoint of the old GRaF layout is refused with the reason, for evaluation, resuming and fine-tuning
    old = torch.load(ckpt, map_location="cpu", weights_only=False)
    old.pop("graf")
    torch.save(old, tmp_path / "old.ckpt")
    why = (
        r"old.ckpt: was written by GRaFModule layout 1; this version reads layout 3 only.*"
        r"layout 2: .*voxel-index table.*; layout 3: each ray's voxels now run from its own entry"
    )
    with pytest.raises(CheckpointError, match=why):
        run("model=graf_cpu", path=tmp_path / "old.ckpt")
    for extra in (
        (f"ckpt_path={tmp_path / 'old.ckpt'}",),
        ("finetune=f100", "finetune.max_steps=1", f"finetune.init_from={tmp_path / 'old.ckpt'}"),
    ):
        with pytest.raises(CheckpointError, match=why):
            train(
                compose_cfg(
                    "train", ("experiment=graf_rfid_s23", "model=graf_cpu", "trainer.max_steps=2", *extra, *FAST)
                )
            )
