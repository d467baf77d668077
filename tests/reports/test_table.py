"""graf-table's reading of results.json files: a run's is read, another command's is passed over, and a file that
holds no run's results is refused in one line (exit code 2) instead of making a blank row."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from graf.errors import ConfigError
from graf.reports.table import collect, read_run_result

RUN = {"method": "knn", "scene": "rfid_s23", "metrics": {"test/psnr": 20.0}, "config": {"task_name": "eval"}}


def test_a_results_json_without_metrics_or_evaluations_is_not_a_run(tmp_path):
    f = tmp_path / "results.json"
    f.write_text(json.dumps({"method": "x"}))
    with pytest.raises(ConfigError, match="not a run's results.json"):
        read_run_result(f)
    f.write_text(json.dumps({"method": "knn", "metrics": None}))
    with pytest.raises(ConfigError, match="neither metrics nor evaluations"):
        read_run_result(f)
    f.write_text(json.dumps({"method": "x", "evaluations": [{"eval_scene": "a", "metrics": {}}]}))
    assert read_run_result(f)["method"] == "x"  # a cross-scene run: its figures per test scene


def test_another_commands_output_beside_the_runs_is_passed_over(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "results.json").write_text(json.dumps(RUN))
    (tmp_path / "_simulate").mkdir()  # graf-pareto simulates a missing scene into its sweep folder
    (tmp_path / "_simulate" / "results.json").write_text(json.dumps({"scene": "s", "config": {"task_name": "x"}}))
    assert [r["method"] for r in collect([tmp_path])] == ["knn"]


def test_graf_table_refuses_a_results_json_that_is_not_a_runs_in_one_line(tmp_path):
    f = tmp_path / "results.json"
    f.write_text(json.dumps({"method": "x"}))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    cmd = [sys.executable, "-m", "graf.cli.table", f"runs={f}", f"hydra.run.dir={tmp_path / 'out'}"]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2, p.stderr[-3000:]
    assert lines[-2] == f"error: {f}: not a run's results.json (it holds neither metrics nor evaluations)", lines
    assert "Traceback" not in p.stderr and "| x |" not in p.stdout
