"""Callbacks: the test predictions for results files and figures, the periodic and final checkpoints, the
pre-emption stop, and the threads a run goes on beside busy processes."""

from __future__ import annotations

import logging
import signal
import threading
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from lightning.pytorch.callbacks import Callback, ModelCheckpoint

from graf.geometry.grid import SPECTRUM_SHAPE
from graf.machine import available_cores, threads_beside_load
from graf.metrics.names import METRIC_NAMES

log = logging.getLogger("graf")
PER_SPECTRUM = METRIC_NAMES  # the test metrics kept per spectrum (arrays ``metric_<name>``): every registered one


class PredictionCollector(Callback):
    """Keeps the test predictions, targets and ids (float32 on CPU) for results files and figures, and each test
    spectrum's metrics (``metric_mse``, ``metric_psnr``, ...: the values the test loop averaged)."""

    def __init__(self):
        self.on_test_epoch_start(None, None)

    def on_test_epoch_start(self, trainer, pl_module) -> None:
        self.pred: list[torch.Tensor] = []
        self.target: list[torch.Tensor] = []
        self.ids: list[torch.Tensor] = []
        self.values: dict[str, list[torch.Tensor]] = {k: [] for k in PER_SPECTRUM}

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self.pred.append(outputs["pred"].detach().float().cpu())
        self.target.append(batch["tgt_spectrum"].detach().float().cpu())
        self.ids.append(batch["tgt_id"].detach().cpu())
        for k, v in (outputs.get("per_spectrum") or {}).items():
            if k in self.values:
                self.values[k].append(v.detach().double().cpu().reshape(-1))

    def arrays(self) -> dict[str, np.ndarray]:
        """The test predictions, targets and ids in the split's order.  Under data-parallel evaluation each rank
        holds every ``world_size``-th spectrum (:meth:`SpectrumDataModule.eval_positions`): the ranks' shares
        are gathered (every rank must call this) and dealt back into order."""
        if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            mine = self._local()
            parts: list = [None] * dist.get_world_size()
            dist.all_gather_object(parts, mine)
            n = sum(len(p["ids"]) for p in parts)
            w = len(parts)
            order = [(i % w, i // w) for i in range(n)]
            return {k: np.stack([parts[r][k][j] for r, j in order]) if n else mine[k] for k in mine}
        return self._local()

    def _local(self) -> dict[str, np.ndarray]:
        n = sum(len(i) for i in self.ids)
        values = {f"metric_{k}": torch.cat(v).numpy() for k, v in self.values.items() if v and sum(map(len, v)) == n}
        if not self.pred:
            return {
                "pred": np.zeros((0, *SPECTRUM_SHAPE), np.float32),
                "target": np.zeros((0, *SPECTRUM_SHAPE), np.float32),
                "ids": np.zeros((0,), np.int64),
            }
        return {
            "pred": torch.cat(self.pred).numpy().astype(np.float32),
            "target": torch.cat(self.target).numpy().astype(np.float32),
            "ids": torch.cat(self.ids).numpy().astype(np.int64),
            **values,
        }


class FinalCheckpoint(ModelCheckpoint):
    """Lightning's ``ModelCheckpoint`` (every ``every_n_train_steps`` steps, ``last.ckpt`` with ``save_last``) that
    also saves the step training ends at.  Lightning's own saves ``last.ckpt`` at the end of training only when it
    has saved nothing before: a run of 60 steps with checkpoints every 50 ended with ``last.ckpt`` at step 50, and
    every reader of ``last.ckpt`` (graf-eval, fine-tuning, graf-curves' next point, a resume with a longer
    ``trainer.max_steps``) would have got stale weights (graf-train refused it, after training)."""

    @property
    def state_key(self) -> str:
        """Lightning's ``ModelCheckpoint``'s: checkpoints written by either resume under the other without warning."""
        return super().state_key.replace(type(self).__qualname__, ModelCheckpoint.__qualname__, 1)

    def on_train_end(self, trainer, pl_module) -> None:
        super().on_train_end(trainer, pl_module)
        if not self._should_skip_saving_checkpoint(trainer):  # not saved at this step yet (nor a sanity check)
            candidates = self._monitor_candidates(trainer)
            if self.monitor is None or self.monitor in candidates:
                self._save_topk_checkpoint(trainer, candidates)
            self._save_last_checkpoint(trainer, candidates)


class TrainingInterrupted(Exception):
    """Ctrl+C (SIGINT) stopped training after the step in progress, its state saved (:attr:`Preemption.saved`)."""


class Preemption(Callback):
    """A SIGTERM during training (a cluster pre-empting the job) or a Ctrl+C (SIGINT) stops the run after the step
    in progress with its state saved.  SIGTERM: Lightning notices the signal (its signal connector sets
    ``trainer.received_sigterm``) and raises ``SIGTERMException`` at the end of that step.  SIGINT: this callback's
    handler, installed for the fit, notes it (a second Ctrl+C stops at once, as Python's own handler does) and
    raises :class:`TrainingInterrupted` at the end of that step.  A SIGTERM that lands in a validation pass stops
    after that validation batch, and one at an epoch's end stops there (Lightning's own checks).  Either way this
    callback first saves ``<dirpath>/last.ckpt`` (the file ``ckpt_path=`` resumes from, optimiser and step count
    included) and records where it stopped in :attr:`saved`.  graf-train then says how to resume and exits with code
    143 (128 + SIGTERM; it writes ``preempted.json``) or 130 (128 + SIGINT)."""

    def __init__(self, dirpath: str):
        self.dirpath = str(dirpath)
        self.saved: dict | None = None
        self.interrupted = False
        self.previous_handler = None

    def on_train_start(self, trainer, pl_module) -> None:
        self.interrupted = False
        if threading.current_thread() is threading.main_thread():
            self.previous_handler = signal.signal(signal.SIGINT, self.on_sigint)

    def on_sigint(self, signum, frame) -> None:
        self.interrupted = True
        self.restore_handler()

    def restore_handler(self) -> None:
        if self.previous_handler is not None:
            signal.signal(signal.SIGINT, self.previous_handler)
            self.previous_handler = None

    def on_train_end(self, trainer, pl_module) -> None:
        self.restore_handler()

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        self.restore_handler()

    def save(self, trainer) -> None:
        """``last.ckpt`` once, when a signal has come (the state after the last optimiser step)."""
        if (trainer.received_sigterm or self.interrupted) and self.saved is None:
            path = Path(self.dirpath) / "last.ckpt"
            trainer.save_checkpoint(str(path))
            self.saved = {"checkpoint": str(path), "global_step": int(trainer.global_step)}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.save(trainer)
        if self.interrupted and not trainer.received_sigterm:
            raise TrainingInterrupted(f"SIGINT at step {int(trainer.global_step)}")

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        # Lightning also stops at a SIGTERM after a validation batch (and at an epoch's end): save there too, or a
        # signal that lands in a validation pass would leave only the newest periodic checkpoint
        if trainer.state.fn == "fit" and not trainer.sanity_checking and trainer.received_sigterm:
            self.save(trainer)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        if trainer.received_sigterm:
            self.save(trainer)


class AttemptClock(Callback):
    """Writes into every checkpoint how long this attempt has trained and from which step it started
    (``checkpoint["graf_attempt"] = {"start_step", "global_step", "fit_s"}``), so that a run killed outright
    (SIGKILL, a lost machine: no ``preempted.json``) still tells graf-curves how many seconds the steps it
    saved cost.  The steps after the newest checkpoint are lost and trained again; their seconds are not counted."""

    def __init__(self):
        self._t0: float | None = None
        self._step0 = 0

    def on_train_start(self, trainer, pl_module) -> None:
        self._t0, self._step0 = time.perf_counter(), int(trainer.global_step)

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        if self._t0 is not None:
            checkpoint["graf_attempt"] = {
                "start_step": self._step0,
                "global_step": int(trainer.global_step),
                "fit_s": round(time.perf_counter() - self._t0, 3),
            }


class TargetCount(Callback):
    """Counts the training targets this run's optimiser steps saw, over every rank (a step of data-parallel
    training sees each rank's batch): :attr:`targets` after ``fit``, and the world size, for results.json."""

    def __init__(self):
        self.local = 0
        self.targets: int | None = None
        self.world_size = 1

    def on_train_start(self, trainer, pl_module) -> None:
        self.local, self.targets = 0, None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.local += int(len(batch["tgt_id"]))

    def on_train_end(self, trainer, pl_module) -> None:
        total = trainer.strategy.reduce(torch.tensor(float(self.local), device=pl_module.device), reduce_op="sum")
        self.targets, self.world_size = int(round(float(total))), int(trainer.world_size)


class ThreadsBesideLoad(Callback):
    """On a CPU, each training, validation and test batch runs on :func:`graf.machine.threads_beside_load` of the
    threads set: all of them on a quiet machine (a seeded run keeps its prediction hash), the cores left beside busy
    processes (measured from CPU time, never guessed from the load average), the threads set again once they stop.
    A change holds for at least ``hold_s`` seconds (a load that comes and goes does not flip the threads every
    batch); the first :data:`LOGGED_CHANGES` changes are logged with what was measured, the rest at debug level;
    :attr:`fewer_batches` counts the batches run on fewer threads."""

    LOGGED_CHANGES = 5

    def __init__(self, hold_s: float = 5.0):
        self.hold_s = float(hold_s)
        self.threads: int | None = None
        self.fewer_batches = 0
        self.changes = 0
        self._changed_at = -float("inf")

    def _adjust(self, pl_module) -> None:
        if pl_module.device.type != "cpu":
            return
        if self.threads is None:
            self.threads = torch.get_num_threads()
        want, other = threads_beside_load(self.threads)
        now = time.monotonic()
        if want != torch.get_num_threads() and now - self._changed_at >= self.hold_s:
            self.changes += 1
            log.log(
                logging.INFO if self.changes <= self.LOGGED_CHANGES else logging.DEBUG,
                "measured: other processes use %s of %d cores: this run goes on %d of the %d torch threads set%s",
                "-" if other is None else f"{other:.2f}", available_cores(), want, self.threads,
                " (further changes at debug level)" if self.changes == self.LOGGED_CHANGES else "",
            )  # fmt: skip
            torch.set_num_threads(want)
            self._changed_at = now
        self.fewer_batches += torch.get_num_threads() < self.threads

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._adjust(pl_module)

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0) -> None:
        self._adjust(pl_module)

    def on_test_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0) -> None:
        self._adjust(pl_module)

    def _restore(self, *args) -> None:
        if self.threads is not None:
            torch.set_num_threads(self.threads)
            self.threads = None

    on_train_end = on_validation_end = on_test_end = _restore
