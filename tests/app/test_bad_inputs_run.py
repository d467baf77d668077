"""Nothing silently wrong, part two (issue 52): a run's bad inputs (a crafted checkpoint, a step count that is no
multiple of the checkpoint interval, an output folder that cannot be used or holds an interrupted run) each end
with one line naming the input and exit code 2, and nothing already written is lost."""

from __future__ import annotations

import errno
import json
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from graf.app.output_folder import OutputFolderCheck
from graf.errors import WriteError
from graf.io import atomic_write_json
from graf.models.base import CheckpointError, read_checkpoint
from graf.run.evaluate import load_checkpoint_model
from graf.run.train import train

BIN = Path(sys.executable).parent
# a tiny KNN-DL run on the embedded scene: a few seconds for 60 steps
TINY = (
    "model=knn_dl",
    "data.batch_size=2",
    "data.test_subset=2",
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


# --------------------------------------------------------------------------------------------- 3. output folders


def _check(tmp_path, folder, capsys, **cfg) -> str:
    config = OmegaConf.create({"hydra": {"run": {"dir": str(folder)}}, "task_name": "train", "ckpt_path": None, **cfg})
    with pytest.raises(SystemExit) as e:
        OutputFolderCheck().on_run_start(config=config)
    assert e.value.code == 2
    return _error_line(capsys.readouterr().err)


def test_an_output_folder_that_is_a_file_or_too_long_a_name_is_one_line(tmp_path, capsys):
    (tmp_path / "afile").write_text("kept")
    line = _check(tmp_path, tmp_path / "afile", capsys)
    assert f"hydra.run.dir={tmp_path / 'afile'}" in line and "is a file, not a folder" in line
    line = _check(tmp_path, tmp_path / "afile" / "run", capsys)
    assert f"{tmp_path / 'afile'} is a file, not a folder" in line
    assert (tmp_path / "afile").read_text() == "kept"
    line = _check(tmp_path, tmp_path / ("x" * 300), capsys)
    assert "x" * 300 in line and "300 bytes long" in line


@pytest.mark.parametrize(
    ("code", "said"),
    [(errno.ENOSPC, "no space is left on its disk"), (errno.EROFS, "read-only"), (errno.EACCES, "permission")],
)
def test_an_output_folder_on_a_full_or_read_only_disk_is_one_line(tmp_path, capsys, monkeypatch, code, said):
    def refuse(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    line = _check(tmp_path, tmp_path / "run", capsys)
    assert f"hydra.run.dir={tmp_path / 'run'}: cannot be this run's output folder" in line and said in line


def test_a_full_disk_at_results_json_is_one_line_and_keeps_the_file_there(tmp_path, monkeypatch):
    atomic_write_json(tmp_path / "results.json", {"old": 1})

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(WriteError, match=r"results.json: cannot be written \(No space left on device\)"):
        atomic_write_json(tmp_path / "results.json", {"new": 2})
    assert json.loads((tmp_path / "results.json").read_text()) == {"old": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["results.json"]  # no temp file left


def test_a_new_run_in_an_interrupted_runs_folder_is_refused_and_keeps_its_checkpoint(tmp_path):
    """graf-train in a folder holding checkpoints/last.ckpt and no results.json overwrote that run's checkpoint (and
    Hydra its .hydra/ first): refused before anything is written, unless the run resumes that checkpoint."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"the interrupted run's state")
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text("- model=knn_dl\n")
    p = _cli("graf-train", "model=knn", "logger=none", "plot_count=0", f"hydra.run.dir={run}", cwd=tmp_path)
    assert p.returncode == 2
    line = _error_line(p.stderr)
    assert f"hydra.run.dir={run}" in line and "interrupted training run" in line
    assert f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}" in line and "another folder" in line
    assert (run / "checkpoints" / "last.ckpt").read_bytes() == b"the interrupted run's state"
    assert (run / ".hydra" / "overrides.yaml").read_text() == "- model=knn_dl\n"
    assert sorted(f.name for f in run.iterdir()) == [".hydra", "checkpoints"]


def test_a_run_resuming_the_interrupted_run_in_its_folder_is_let_in(tmp_path, capsys):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    last = run / "checkpoints" / "last.ckpt"
    last.write_bytes(b"state")
    for task_name in ("train", "graf_rfid_s23"):  # graf-train of an experiment that names its task (graf-curves)
        config = OmegaConf.create(
            {
                "hydra": {"run": {"dir": str(run)}, "job": {"name": "train"}},
                "task_name": task_name,
                "ckpt_path": str(last),
            }
        )
        OutputFolderCheck().on_run_start(config=config)  # no exit
    line = _check(tmp_path, run, capsys, ckpt_path=str(tmp_path / "other.ckpt"))
    assert "interrupted training run" in line
    # graf-eval writing its results.json beside the interrupted checkpoint, even one testing it: refused
    line = _check(
        tmp_path, run, capsys, hydra={"run": {"dir": str(run)}, "job": {"name": "evaluate"}}, ckpt_path=str(last)
    )
    assert "interrupted training run" in line


def test_a_run_folder_in_use_is_locked_and_a_second_run_into_it_stops_with_one_line(tmp_path):
    """Two runs into one folder (issue 68): the second stops with one line naming the first's process, instead of
    both finishing and only the later one's results remaining; the lock goes with the process that held it."""
    import time

    from graf.app.output_folder import LOCK_NAME, lock_folder

    # another run holding the folder: the lock as lock_folder takes it (an flock on the file, its pid written)
    hold = "import fcntl, os, sys, time\nfd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)\n"
    hold += "fcntl.flock(fd, fcntl.LOCK_EX)\nos.write(fd, f'{os.getpid()}\\n'.encode())\nprint('held', flush=True)\n"
    hold += "time.sleep(30)\n"
    p = subprocess.Popen([sys.executable, "-c", hold, str(tmp_path / LOCK_NAME)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        why = lock_folder(tmp_path)
        assert why is not None and f"another run (process {p.pid}) is writing into it" in why
        assert str(tmp_path / LOCK_NAME) in why
    finally:
        p.kill()
        p.wait()
    deadline = time.monotonic() + 10
    while lock_folder(tmp_path) is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert lock_folder(tmp_path) is None  # the holder is gone: free; held now by this process, again: still ours
    assert lock_folder(tmp_path) is None


def test_a_disk_that_fills_mid_run_ends_on_one_line_naming_the_file():
    """A full disk met by a writer that is not graf's own atomic one (a checkpoint's torch.save, a logger): a user
    error of one line naming the file (issue 68), found through a library's wrapping; other OSErrors stay bugs."""
    from graf.errors import disk_full, is_user_error, user_message

    full = OSError(errno.ENOSPC, "No space left on device", "/run/checkpoints/last.ckpt")
    try:
        try:
            raise full
        except OSError as e:
            raise RuntimeError("checkpoint could not be saved") from e
    except RuntimeError as wrapped:
        assert is_user_error(wrapped)
        assert user_message(wrapped) == (
            "no space is left on the disk (No space left on device, writing /run/checkpoints/last.ckpt); the files "
            "written before are kept"
        )
        cfg = OmegaConf.create({"paths": {"output_dir": "/run"}})
        assert user_message(wrapped, cfg).startswith("no space is left on the disk of /run (")
    torch_said = RuntimeError("[enforce fail at inline_container.cc:664] . unexpected pos ... No space left on device")
    assert disk_full(torch_said).startswith("no space is left on the disk ([enforce fail")
    assert disk_full(OSError(errno.EIO, "I/O error")) is None and not is_user_error(OSError(errno.EIO, "I/O error"))
