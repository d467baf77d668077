"""The studies' subprocess runner (graf.studies.runner), and graf-pareto's sweep driving it: a run's outcome, a
SIGTERM passed on, and the commands, skips and failures of one sweep (the runs faked, so it takes a second)."""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from graf.app.config import CONF_DIR
from graf.errors import PREEMPTED_EXIT_CODE, Preempted
from graf.studies import pareto
from graf.studies.runner import run_command


def _wait_for(path: Path, text: str, timeout: float = 30.0) -> None:
    end = time.time() + timeout
    while time.time() < end:
        if path.exists() and text in path.read_text():
            return
        time.sleep(0.05)


def test_a_sigterm_is_passed_to_the_run_and_stops_the_command_with_code_143(tmp_path):
    """graf-curves and graf-pareto run graf-train one job after another: a SIGTERM to them reaches the job in
    progress (which saves its state), and the command stops with Preempted instead of going on to its next job."""
    child = tmp_path / "child.py"
    child.write_text(
        "import signal, sys, time, pathlib\n"
        "def stop(*a):\n"
        f"    pathlib.Path({str(tmp_path / 'got_sigterm')!r}).write_text('saved')\n"
        "    sys.exit(143)\n"
        "signal.signal(signal.SIGTERM, stop)\n"
        "print('started', flush=True)\n"
        "time.sleep(60)\n"
    )
    started = tmp_path / "job" / "run.log"
    before = signal.getsignal(signal.SIGTERM)
    t = threading.Thread(target=lambda: (_wait_for(started, "started"), os.kill(os.getpid(), signal.SIGTERM)))
    t.start()
    with pytest.raises(Preempted) as exc:
        run_command([sys.executable, str(child)], tmp_path / "job", dict(os.environ), timeout=60)
    t.join()
    assert exc.value.exit_code == PREEMPTED_EXIT_CODE and "exit code 143" in str(exc.value)
    assert (tmp_path / "got_sigterm").read_text() == "saved"
    assert signal.getsignal(signal.SIGTERM) is before  # the handler before run_command is back
    ok, _ = run_command([sys.executable, "-c", "print('done')"], tmp_path / "job2", dict(os.environ), timeout=60)
    assert not ok  # it wrote no results.json; an ordinary failure, not a pre-emption


def test_a_run_is_ok_with_results_and_a_run_past_its_timeout_is_killed(tmp_path):
    write = "import pathlib, sys; print('line'); pathlib.Path(sys.argv[1], 'results.json').write_text('{}')"
    ok, tail = run_command([sys.executable, "-c", write, str(tmp_path / "a")], tmp_path / "a", dict(os.environ), 60)
    assert ok and tail == "line" and (tmp_path / "a" / "run.log").read_text() == "line\n"
    t0 = time.perf_counter()
    ok, _ = run_command([sys.executable, "-c", "import time; time.sleep(60)"], tmp_path / "b", dict(os.environ), 1)
    assert not ok and time.perf_counter() - t0 < 30


def _fake_run(calls: list, broken: str):
    """A stand-in for run_command: records the command; a run writes a results.json (graf-train's base also its
    checkpoint), except the point ``broken``, which fails."""

    def run(cmd, folder, env, timeout):
        calls.append((folder.name, cmd, env.get("OMP_NUM_THREADS")))
        folder.mkdir(parents=True, exist_ok=True)
        if folder.name == broken:
            return False, "boom"
        if folder.name == "base":
            (folder / "checkpoints").mkdir()
            (folder / "checkpoints" / "last.ckpt").write_text("")
        timing = {"fit_s": 10.0, "fit_s_per_step": 0.1, "test_s_per_spectrum": 0.5 if folder.name == "base" else 0.2}
        result = {"timing": timing, "metrics": {"val/psnr": 20.0, "test/psnr": 19.0}}
        (folder / "results.json").write_text(json.dumps(result))
        return True, "ok"

    return run


def test_a_pareto_sweep_runs_each_point_once_records_a_failure_and_resumes(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(pareto, "run_command", _fake_run(calls, broken="voxel_2"))
    monkeypatch.setattr(pareto, "plot", lambda path, rows: None)  # the figure is not the subject here
    overrides = [f"out={tmp_path}", f"paths.output_dir={tmp_path}", "threads=1", "only_scenes=[rfid_s23_sparse]"]
    overrides.append("only_points=[base,voxel_2,L_test_3]")
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("pareto", overrides=overrides)
    r = pareto.sweep(cfg)
    assert [c[0] for c in calls] == ["base", "voxel_2", "L_test_3"] and {c[2] for c in calls} == {"1"}
    train, evaluate = calls[0][1], calls[2][1]
    assert train[1:3] == ["-m", "graf.cli.train"] and "experiment=graf_rfid_s23" in train  # the base: the main job
    assert train[-1] == f"hydra.run.dir={tmp_path / 'rfid_s23_sparse' / 'base'}"
    ckpt = tmp_path / "rfid_s23_sparse" / "base" / "checkpoints" / "last.ckpt"
    assert evaluate[1:4] == ["-m", "graf.cli.evaluate", f"ckpt_path={ckpt}"] and "neighbors.L=3" in evaluate
    assert [f["point"] for f in r["failed"]] == ["voxel_2"] and r["failed"][0]["log"] == "boom"
    rows = {row["point"]: row for row in r["rows"]}
    assert set(rows) == {"base", "L_test_3"} and rows["L_test_3"]["train_s"] == rows["base"]["train_s"]
    assert rows["L_test_3"]["front_infer"] and not rows["base"]["front_infer"]  # as good, and faster
    written = json.loads((tmp_path / "results.json").read_text())
    assert written["rows"] == r["rows"] and json.loads((tmp_path / "failed.json").read_text()) == r["failed"]
    # resuming: only the failed point runs again
    calls.clear()
    monkeypatch.setattr(pareto, "run_command", _fake_run(calls, broken="none"))
    r = pareto.sweep(cfg)
    assert [c[0] for c in calls] == ["voxel_2"] and len(r["rows"]) == 3
