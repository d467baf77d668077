"""Data-parallel training and evaluation with Lightning DDP (issue 25, part 1), on CPU processes over gloo: each rank
draws its own batches from the step-indexed stream, each test spectrum is evaluated once and the metrics are summed
across ranks, and rank 0 alone writes."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from graf.bands import Band
from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector
from graf.data.scenes import NeRF2Scene

S23, BAND = NeRF2Scene("rfid_s23", "embedded:rfid_s23_200"), Band("915mhz", 915e6)


def _dm(trainer=None) -> SpectrumDataModule:
    dm = SpectrumDataModule(S23, BAND, NeighborSelector(L=10, L_train=(3, 10), radius=10.0), batch_size=4)
    dm.setup()
    if trainer is not None:
        dm.trainer = trainer
    return dm


def _rank(r: int, w: int, step: int = 0):
    return SimpleNamespace(global_rank=r, world_size=w, global_step=step, accumulate_grad_batches=1)


def test_each_rank_draws_its_own_batch_of_the_step_indexed_stream():
    one = _dm()
    for k in (0, 3, 40):  # steps within and across epochs (36 batches of 4 per epoch)
        b0, b1 = _dm(_rank(0, 2)).rank_batch(k), _dm(_rank(1, 2)).rank_batch(k)
        # rank r's batch at step k is the stream's draw 2k + r: what one process would draw as batches 2k, 2k+1
        for b, g in ((b0, 2 * k), (b1, 2 * k + 1)):
            ref = one.train_batch(g)
            assert torch.equal(b["tgt_id"], ref["tgt_id"]) and torch.equal(b["src_index"], ref["src_index"])
        assert not set(b0["tgt_id"].tolist()) & set(b1["tgt_id"].tolist())  # two ranks, two different draws
        # a pure function of (seed, step, rank): a resumed run draws the same
        assert torch.equal(_dm(_rank(1, 2)).rank_batch(k)["tgt_id"], b1["tgt_id"])
    assert torch.equal(_dm(_rank(0, 1)).rank_batch(5)["tgt_id"], one.train_batch(5)["tgt_id"])


def test_evaluation_positions_are_dealt_to_the_ranks_once_each():
    dm = _dm()
    for w in (1, 2, 3):
        shares = []
        for r in range(w):
            dm.trainer = _rank(r, w)
            shares.append(dm.eval_positions(11))
        assert sorted(sum(shares, [])) == list(range(11))  # every position once: no padding, no duplicate
        assert max(map(len, shares)) - min(map(len, shares)) <= 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(tmp: Path, module: str, *args: str, procs: int = 1) -> dict:
    out = tmp / f"{module.rsplit('.', 1)[1]}_{procs}"
    common = ["logger=none", "plot_count=0", f"hydra.run.dir={out}", f"data_root={tmp / 'data'}", *args]
    if procs == 1:
        cmd = [sys.executable, "-m", module, *common]
    else:  # torchrun sets RANK / WORLD_SIZE / MASTER_PORT for each process, as srun does on a cluster
        run = [sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={procs}", "--nnodes=1"]
        cmd = [*run, f"--master_port={_free_port()}", "-m", module, "trainer=ddp", f"trainer.devices={procs}", *common]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    return {"results": json.loads((out / "results.json").read_text()), "dir": out, "stdout": p.stdout}


@pytest.mark.slow  # two trainings and two evaluations, one and two processes each: about two minutes here
def test_two_gloo_processes_test_like_one_and_a_step_sees_twice_the_targets(tmp_path):
    one = _run(tmp_path, "graf.cli.train", "model=knn_dl", "trainer.max_steps=2")
    two = _run(tmp_path, "graf.cli.train", "model=knn_dl", "trainer.max_steps=2", procs=2)
    t1, t2 = one["results"]["training"], two["results"]["training"]
    assert (t1["world_size"], t2["world_size"]) == (1, 2)
    assert t2["targets_seen"] == 2 * t1["targets_seen"] == 2 * 2 * 4  # 2 steps of 4 targets per rank
    assert two["results"]["n_test"] == one["results"]["n_test"] == 40  # each test spectrum counted once
    assert two["stdout"].count("results:") == 1  # one rank reports and writes

    # the same weights evaluated by one process and by two: the same figures, the same predictions in order
    ckpt = one["dir"] / "checkpoints" / "last.ckpt"
    e1 = _run(tmp_path, "graf.cli.evaluate", f"ckpt_path={ckpt}", "save_predictions=true")
    e2 = _run(tmp_path, "graf.cli.evaluate", f"ckpt_path={ckpt}", "save_predictions=true", procs=2)
    m1, m2 = e1["results"]["metrics"], e2["results"]["metrics"]
    for k in m1:
        assert (m1[k] is None and m2[k] is None) or m2[k] == pytest.approx(m1[k], abs=1e-6), k
    p1, p2 = np.load(e1["dir"] / "predictions.npz"), np.load(e2["dir"] / "predictions.npz")
    assert np.array_equal(p1["ids"], p2["ids"]) and np.allclose(p1["pred"], p2["pred"], atol=1e-6)


def test_the_ddp_preset_composes_alone_and_after_a_gpu_preset():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from graf.app.config import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        alone = compose("train", ["trainer=ddp"]).trainer
        gpu = compose("train", ["trainer=[gpu_bf16,ddp_strategy]", "trainer.devices=4"]).trainer
    GlobalHydra.instance().clear()
    assert (alone.strategy, alone.devices, alone.accelerator, alone.precision, alone.use_distributed_sampler) == (
        "ddp", 2, "auto", "32-true", False)  # fmt: skip
    assert (gpu.strategy, gpu.devices, gpu.accelerator, gpu.precision, gpu.float32_matmul_precision) == (
        "ddp", 4, "gpu", "bf16-mixed", "high")  # fmt: skip


def test_under_ddp_rank_0_alone_reports_to_the_pruner_and_every_rank_takes_its_decision():
    import optuna

    from graf.search.pruning import OptunaPruning

    study = optuna.create_study(direction="maximize", pruner=optuna.pruners.MedianPruner(n_startup_trials=1))
    done = study.ask()
    done.report(10.0, 2)
    study.tell(done, 10.0)
    sent = []

    def trainer(rank: int, decision_of_rank_0: bool | None = None):
        def broadcast(value, src=0):
            sent.append((rank, value))
            return value if decision_of_rank_0 is None else decision_of_rank_0

        return SimpleNamespace(sanity_checking=False, global_step=2, max_steps=10, is_global_zero=rank == 0,
                               world_size=2, callback_metrics={"val/psnr": torch.tensor(-10.0)},
                               strategy=SimpleNamespace(broadcast=broadcast))  # fmt: skip

    trial = study.ask()
    with pytest.raises(optuna.TrialPruned):
        OptunaPruning(trial, "val/psnr").on_validation_end(trainer(0), None)  # under the median: rank 0 prunes
    with pytest.raises(optuna.TrialPruned):  # rank 1 asks nothing and reports nothing: it takes rank 0's decision
        OptunaPruning(trial, "val/psnr").on_validation_end(trainer(1, decision_of_rank_0=True), None)
    assert sent == [(0, True), (1, False)]
    assert study.trials[1].intermediate_values == {2: -10.0}  # one report, from rank 0


def test_a_run_started_as_several_processes_without_a_shared_folder_is_refused(tmp_path):
    # torchrun / srun start every rank with the same command: the default folder names the second each started in
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "1"}
    p = subprocess.run([sys.executable, "-m", "graf.cli.train", "model=knn", "logger=none"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300, env=env)  # fmt: skip
    assert p.returncode == 2  # a user error's exit code
    assert "2 processes were started for this run (torchrun / srun)" in p.stderr
    assert "hydra.run.dir=outputs/ddp_run" in p.stderr
    assert "Traceback" not in p.stderr and not list(tmp_path.rglob("results.json"))


@pytest.mark.slow  # a base model and its fine-tuning, both by two gloo processes: about a minute here
def test_under_ddp_a_base_model_trained_on_the_fly_is_trained_by_every_rank_then_fine_tuned(tmp_path):
    base = tmp_path / "base"
    study = ["finetune=f50", "finetune.init_from=base", "finetune.max_steps=3",
             f"finetune.base={{dir:'{base}',overrides:['model=knn_dl']}}"]  # fmt: skip
    two = _run(tmp_path, "graf.cli.train", "model=knn_dl", "trainer.max_steps=2", *study, procs=2)
    b = json.loads((base / "results.json").read_text())
    assert b["training"]["world_size"] == 2 and b["global_step"] == 2  # the ranks trained the base together
    r = two["results"]
    assert r["training"]["world_size"] == 2 and r["training"]["targets_seen"] == 3 * 2 * 4
    assert r["finetune"]["init_from"] == str(base / "checkpoints" / "last.ckpt") and r["finetune"]["base_steps"] == 2
    assert two["stdout"].count("results:") == 2  # the base's and the fine-tuned run's, each printed by rank 0 once
