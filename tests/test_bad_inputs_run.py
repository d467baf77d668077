"""Nothing silently wrong, part two (issue 52): a run's bad inputs (a crafted checkpoint, a step count that is no
multiple of the checkpoint interval, an output folder that cannot be used or holds an interrupted run) each end
with one line naming the input and exit code 2, and nothing already written is lost."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from graf.models.base import CheckpointError, read_checkpoint
from graf.run.evaluate import load_checkpoint_model
from graf.run.train import train

BIN = Path(sys.executable).parent
# a tiny KNN-DL run on the embedded scene: a few seconds for 60 steps
TINY = (
    "model=knn_dl",
    "data.batch_size=2",
    "trainer.limit_test_batches=1",
    "plot_count=0",
    "baselines=null",
    "reliance=false",
    "validate=false",
)


def _cli(cmd: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline", "HYDRA_FULL_ERROR": "0"}
    return subprocess.run([str(BIN / cmd), *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=240)


def _error_line(stderr: str) -> str:
    """The one error line of a command that failed on a user error (Hydra's hint aside)."""
    lines = [ln for ln in stderr.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr[-3000:]
    return lines[0]


# ---------------------------------------------------------------------------------------- 1. a checkpoint runs code


class Payload:
    """Unpickled with pickle's full powers, this runs a shell command that writes the marker file."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def _crafted(path: Path, marker: Path, as_torch: bool = True) -> Path:
    obj = {"state_dict": {}, "global_step": 1, "hyper_parameters": {"x": Payload(marker)}}
    if as_torch:
        torch.save(obj, path)
    else:
        path.write_bytes(pickle.dumps(obj))
    return path


def test_graf_eval_of_a_crafted_checkpoint_refuses_it_and_never_runs_its_payload(tmp_path):
    marker = tmp_path / "marker"
    ckpt = _crafted(tmp_path / "evil.ckpt", marker)
    p = _cli("graf-eval", f"ckpt_path={ckpt}", "logger=none", f"hydra.run.dir={tmp_path / 'o'}", cwd=tmp_path)
    assert p.returncode == 2
    line = _error_line(p.stderr)
    assert str(ckpt) in line and "is not a checkpoint of this project" in line and "posix.system" in line
    assert not marker.exists()


@pytest.mark.parametrize("as_torch", [True, False], ids=["torch.save", "plain-pickle"])
def test_reading_or_resuming_a_crafted_checkpoint_never_runs_its_payload(compose_cfg, tmp_path, as_torch):
    marker = tmp_path / "marker"
    ckpt = _crafted(tmp_path / "evil.ckpt", marker, as_torch)
    with pytest.raises(CheckpointError, match=str(ckpt)):
        read_checkpoint(ckpt)
    with pytest.raises(CheckpointError, match=str(ckpt)):  # graf-train's resume
        train(compose_cfg("train", (*TINY, "trainer.max_steps=2", f"ckpt_path={ckpt}")))
    assert not marker.exists()


def test_unreadable_files_are_one_line_errors(tmp_path):
    (tmp_path / "empty.ckpt").write_bytes(b"")
    (tmp_path / "noise.ckpt").write_bytes(bytes(range(256)) * 4)
    for name in ("empty.ckpt", "noise.ckpt"):
        with pytest.raises(CheckpointError, match="is not a readable checkpoint") as e:
            read_checkpoint(tmp_path / name)
        assert "\n" not in str(e.value) and str(tmp_path / name) in str(e.value)


def test_a_checkpoint_with_omegaconf_hyperparameters_still_loads(tmp_path):
    """Lightning saves a model's hyperparameters as given: OmegaConf containers are on the allow-list."""
    hp = OmegaConf.create({"features": {"name": "ray", "sizes": [1, 2.5, None, True, "x"]}})
    torch.save({"state_dict": {"w": torch.ones(2)}, "hyper_parameters": hp, "global_step": 3}, tmp_path / "ok.ckpt")
    ckpt = read_checkpoint(tmp_path / "ok.ckpt")
    assert ckpt["hyper_parameters"].features.sizes[1] == 2.5 and ckpt["global_step"] == 3


def test_a_checkpoint_naming_a_foreign_class_does_not_import_it(tmp_path, monkeypatch):
    """graf-eval takes the class from the checkpoint: a module the checkpoint names is imported only when it is
    one of graf's methods (importing a module runs its code)."""
    marker = tmp_path / "imported"
    (tmp_path / "foreign_module_52.py").write_text(f"open({str(marker)!r}, 'w').close()\nclass M: pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    torch.save({"state_dict": {}, "graf": {"target": "foreign_module_52.M"}}, tmp_path / "f.ckpt")
    cfg = OmegaConf.create({"model": {"_target_": "graf.models.knn_dl.KNNDLModule"}})
    with pytest.raises(CheckpointError, match="foreign_module_52.M.*not one of graf's methods"):
        load_checkpoint_model(cfg, str(tmp_path / "f.ckpt"), [])
    assert not marker.exists()
    torch.save({"state_dict": {}, "graf": {"target": "graf.errors.UserError"}}, tmp_path / "g.ckpt")
    with pytest.raises(CheckpointError, match="graf.errors.UserError, which is not one of graf's methods"):
        load_checkpoint_model(cfg, str(tmp_path / "g.ckpt"), [])


# ------------------------------------------------------------------- 2. a step count not a multiple of 50 finishes


def test_a_step_count_off_the_checkpoint_interval_finishes_with_last_ckpt_at_the_final_step(compose_cfg, tmp_path):
    """trainer.max_steps=60 with a checkpoint every 50 steps: Lightning saved last.ckpt at the end only when it had
    saved nothing before, so last.ckpt held step 50 and graf-train refused the run after training (no
    results.json, exit code 2).  The run, and a resume of it to 64 steps, now finish with last.ckpt at their end."""
    cfg = compose_cfg("train", (*TINY, "trainer.max_steps=60"))
    assert cfg.callbacks.model_checkpoint.every_n_train_steps == 50
    out = Path(cfg.paths.output_dir)
    train(cfg)
    last = out / "checkpoints" / "last.ckpt"
    assert json.loads((out / "results.json").read_text())["global_step"] == 60
    assert read_checkpoint(last)["global_step"] == 60
    train(compose_cfg("train", (*TINY, "trainer.max_steps=64", f"ckpt_path={last}")))
    assert json.loads((out / "results.json").read_text())["global_step"] == 64
    assert read_checkpoint(last)["global_step"] == 64
