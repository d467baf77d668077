"""scripts/gpu_check.sh at its toy sizes on this CPU (the GPU machine runs the same steps at the paper's sizes):
each step runs, and the summary holds the bench rows of both precisions and the main job's test figures."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_gpu_check_runs_at_toy_sizes_on_a_cpu(tmp_path):
    env = {**os.environ, "PYTHON": sys.executable, "GRAF_GPU_CHECK_OUT": str(tmp_path / "out")}
    p = subprocess.run(
        ["bash", "scripts/gpu_check.sh", "--tiny", str(tmp_path / "no_prepared_folder")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    summary = json.loads((tmp_path / "out" / "gpu_check.json").read_text())
    assert summary["device"] == "cpu" and summary["tiny"] is True
    assert set(summary["steps"]) == {"install", "bench_fp32", "bench_bf16", "main_job"}
    assert all(s["exit_status"] == 0 and s["seconds"] >= 0 for s in summary["steps"].values())
    rows = {(b["precision"], b["preset"]) for b in summary["bench"] if not b["error"]}
    assert rows == {(p, m) for p in ("fp32", "bf16") for m in ("graf", "nerf2")}
    assert all(b["infer_s_per_spectrum"] > 0 and b["train_s_per_step"] > 0 for b in summary["bench"])
    job = summary["main_job"]
    assert job["method"] == "graf-ray-weights" and job["global_step"] == 2
    assert {"test/psnr", "test/ssim", "test/lpips"} <= set(job["metrics"])
    assert "| bf16 | rfid_s23 | nerf2 |" in (tmp_path / "out" / "gpu_check.md").read_text()
