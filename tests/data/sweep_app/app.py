"""A tiny Hydra app for the Optuna sweeper's tests (tests/test_optuna_sweeper.py): no torch, a trial takes
milliseconds.  Each trial writes ``started_x<x>_<pid>`` and, when it ends normally, ``finished_x<x>`` into
``marks`` (the configurations actually trained); ``slow_at`` (or $SWEEP_APP_SLOW_AT) sleeps (to be killed),
``raise_at`` raises,
``nan_at`` returns NaN, ``preempt_at`` stops the first trial with that x as a pre-empted graf-train does (an
exception with ``exit_code`` 143).  ``lightning=true``: a trial trains a tiny Lightning model with validation every 2
steps
and graf's pruning callback; the first trial to run logs val/psnr 10, every later one -10 (so a median
pruner prunes them)."""

import math
import os
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig


class Preempted(Exception):
    exit_code = 143  # as graf.errors.Preempted


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float:
    marks = Path(cfg.marks)
    marks.mkdir(parents=True, exist_ok=True)
    x = int(cfg.x)
    (marks / f"started_x{x}_{os.getpid()}").write_text(str(cfg.get("torch_threads")))
    slow_at = os.environ.get("SWEEP_APP_SLOW_AT", cfg.slow_at)
    if slow_at is not None and x == int(slow_at):
        time.sleep(float(cfg.slow_s))
    if cfg.raise_at is not None and x == int(cfg.raise_at):
        raise RuntimeError(f"trial with x={x} fails on purpose")
    if cfg.preempt_at is not None and x == int(cfg.preempt_at) and not (marks / "preempted_once").exists():
        (marks / "preempted_once").touch()
        raise Preempted(f"SIGTERM: trial with x={x} pre-empted on purpose")
    time.sleep(float(cfg.work_s))
    if cfg.lightning:
        return lightning_trial(cfg, marks)
    with open(marks / f"finished_x{x}", "a") as f:  # appended: a configuration trained twice shows 2 lines
        f.write(f"{os.getpid()}\n")
    if cfg.nan_at is not None and x == int(cfg.nan_at):
        return math.nan
    return -float((x - 3) ** 2)


def lightning_trial(cfg: DictConfig, marks: Path) -> float:
    import lightning as L
    import torch

    from graf.search.pruning import pruning_callback

    first = not (marks / "lightning_first").exists()
    (marks / "lightning_first").touch()
    value = 10.0 if first else -10.0

    class Tiny(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.lin = torch.nn.Linear(1, 1)

        def training_step(self, batch, i):
            return self.lin(batch[0]).pow(2).mean()

        def validation_step(self, batch, i):
            self.log("val/psnr", torch.tensor(value))

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.01)

    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(8, 1)), batch_size=2)
    trainer = L.Trainer(
        max_steps=6,
        val_check_interval=2,
        check_val_every_n_epoch=None,
        limit_val_batches=1,
        callbacks=[pruning_callback(cfg.optuna_trial)],
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
    )
    trainer.fit(Tiny(), data, data)
    with open(marks / f"finished_x{int(cfg.x)}", "a") as f:
        f.write(f"{os.getpid()}\n")
    return value


if __name__ == "__main__":
    main()
