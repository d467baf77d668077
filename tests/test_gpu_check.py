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
    assert set(summary["steps"]) == {"install", "bench_fp32", "bench_bf16", "step_profile", "main_job"}
    assert all(s["exit_status"] == 0 and s["seconds"] >= 0 for s in summary["steps"].values())
    rows = {(b["precision"], b["preset"]) for b in summary["bench"] if not b["error"]}
    assert rows == {(p, m) for p in ("fp32", "bf16") for m in ("graf", "nerf2")}
    assert all(b["infer_s_per_spectrum"] > 0 and b["train_s_per_step"] > 0 for b in summary["bench"])
    assert all(b["trusted"] is (not b["disturbed"]) for b in summary["bench"] if not b["error"])
    paths = {(r["precision"], r["path"]) for r in summary["step_profile"] if "error" not in r}
    assert paths == {(p, q) for p in ("fp32", "bf16") for q in ("grouped", "static")}
    assert summary["profile"]["host_reads_per_step"] == 0  # the static path reads nothing back
    assert summary["profile"]["operator_calls_per_step"] > 0
    job = summary["main_job"]
    assert job["method"] == "graf-ray-weights" and job["global_step"] == 2 and job["train_seconds"] > 0
    assert {"test/psnr", "test/ssim", "test/lpips"} <= set(job["metrics"])
    assert "| bf16 | rfid_s23 | nerf2 |" in (tmp_path / "out" / "gpu_check.md").read_text()


# the packages pyproject.toml installs that a lent GPU machine's image lacks (its list: the device notes), and the
# ray tracer, which such a machine does not need (graf.sim.slim carries the catalog)
MISSING_ON_GPU_MACHINES = ("optuna", "wandb", "sionna", "mitsuba", "drjit")
COMPOSE_AND_BUILD = """
import sys
for name in {missing!r}:
    sys.modules[name] = None  # import fails as if not installed
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from graf.run.build import instantiate_group
with initialize_config_dir(config_dir={conf!r}, version_base="1.3"):
    for experiment in ("cross_scene_matrix", "neighbor_count", "graf_rfid_s23"):
        overrides = [f"experiment={{experiment}}", "logger=csv", "paths.output_dir={out}"]
        cfg = compose("train", overrides=overrides, return_hydra_config=True)
        HydraConfig.instance().set_config(cfg)
        made = instantiate_group(cfg, "callbacks") + instantiate_group(cfg, "logger")
        print(experiment, sorted(type(x).__name__ for x in made))
"""


def test_a_study_job_builds_without_the_packages_a_gpu_machine_lacks(tmp_path):
    """The first paper-density GPU run lost every job to ``import optuna`` (the pruning callback's module) on a
    machine without Optuna: a run that is no search trial must build its callbacks and loggers without it."""
    code = COMPOSE_AND_BUILD.format(missing=MISSING_ON_GPU_MACHINES, conf=str(ROOT / "conf"), out=str(tmp_path))
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-3000:]
    lines = p.stdout.strip().splitlines()
    assert [line.split()[0] for line in lines] == ["cross_scene_matrix", "neighbor_count", "graf_rfid_s23"]
    assert all(
        "FinalCheckpoint" in line for line in lines
    )  # graf.callbacks: a ModelCheckpoint that saves the last step
