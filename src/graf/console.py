"""What a reader of the console sees.

- :func:`filter_known_warnings`: the one place where third-party warnings that are understood are filtered, each
  with the reason it may be ignored here (``KNOWN_WARNINGS``); every command calls it first
  (:func:`graf.cli.entry.cli_errors`).  Warnings of graf's own (a neighbor radius widened, a capped sample
  count) are never filtered.
- :func:`progress_bar`: the training progress callback (the ``callbacks`` group's ``progress_bar``): Lightning's
  redrawing bar on a terminal; on anything else (a log file, a pipe, CI) :class:`LineProgress`, one line every
  ``every_n_steps`` optimiser steps, so that a log holds a few lines instead of thousands of redraws.
"""

from __future__ import annotations

import logging
import sys
import time
import warnings

from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress import ProgressBar

# (message regex, the reason it is understood and may be ignored here)
KNOWN_WARNINGS: tuple[tuple[str, str], ...] = (
    (
        r".*isinstance\(treespec, LeafSpec\)` is deprecated",
        "Lightning 2.6.6's own pytree helper (lightning/pytorch/utilities/_pytree.py) calls an API that torch 2.13 "
        "deprecates; nothing of graf's calls it, and it still works in the pinned torch",
    ),
    (
        r"Your `IterableDataset` has `__len__` defined",
        "graf's training stream (graf.data.datamodule) defines __len__ for the progress bar and gives each "
        "DataLoader worker its own share of the batches (k % num_workers == worker id), so the length is exact "
        "for any num_workers",
    ),
    (
        r"The dirpath has changed from",
        "a search trial re-queued after a pre-emption resumes the pre-empted trial's checkpoint in its own folder; "
        "ModelCheckpoint's best-k bookkeeping, which it says is not reloaded, is not used (save_top_k=1 on last)",
    ),
    (
        r"(Argument ``heartbeat_interval`` is an|.*fail_stale_trials is) experimental",
        "Optuna marks RDBStorage's heartbeats experimental (since 2.9, unchanged through 5.0); a study shared "
        "on PostgreSQL uses them to find dead workers (graf.sweeper.storage.make_storage), as the issue asks",
    ),
    (
        r"You have overridden `on_before_batch_transfer` in `LightningModule` but have passed in a",
        "GRaF reads its batch's scene-table keys on the host before the batch moves (GRaFModule."
        "on_before_batch_transfer, the static path); the datamodule defines no such hook, so the module's runs, "
        "which is what Lightning says it does",
    ),
    (
        r"The number of training batches \(\d+\) is smaller than the logging interval",
        "a short run (a smoke test, a two-step test) logs less often than log_every_n_steps asks; the final "
        "figures come from the evaluation after training, not from the training log",
    ),
)

# Lightning's advertising lines (rank_zero_info on its own loggers): nothing a graf user needs
_TIP = "💡 Tip:"


class _DropTips(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.getMessage()).startswith(_TIP)


def filter_known_warnings() -> None:
    """Filter the understood third-party warnings (``KNOWN_WARNINGS``) and Lightning's tips; idempotent."""
    for pattern, _reason in KNOWN_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)
    for name in ("lightning.pytorch", "lightning.pytorch.utilities.rank_zero", "lightning.fabric"):
        lg = logging.getLogger(name)
        if not any(isinstance(f, _DropTips) for f in lg.filters):
            lg.addFilter(_DropTips())


def is_terminal(stream=None) -> bool:
    stream = sys.stdout if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class LineProgress(ProgressBar):
    """A training progress line every ``every_n_steps`` optimiser steps and at the last one::

        step 100/300  train/loss 0.0214  2.31 steps/s

    Validation and test loops print nothing (their figures end the command, in its table)."""

    def __init__(self, every_n_steps: int = 50, stream=None) -> None:
        super().__init__()
        if isinstance(every_n_steps, bool) or not isinstance(every_n_steps, int) or every_n_steps < 1:
            raise ValueError(f"every_n_steps must be an integer >= 1, got {every_n_steps!r}")
        self.every_n_steps, self.stream = every_n_steps, stream
        self._enabled, self._t0, self._step0, self._printed = True, None, 0, -1

    # disable/enable: Lightning's ProgressBar interface (its base raises NotImplementedError).  Lightning disables
    # the bar on every rank but the first (DDP); its Tuner (lr_find, scale_batch_size) disables it and enables
    # it again around its trial runs.
    def disable(self) -> None:
        self._enabled = False

    def enable(self) -> None:
        self._enabled = True

    def on_train_start(self, trainer, pl_module) -> None:
        self._t0, self._step0, self._printed = time.perf_counter(), int(trainer.global_step), -1

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step, total = int(trainer.global_step), int(trainer.max_steps)
        last = total > 0 and step >= total
        if not self._enabled or step == self._printed or (step % self.every_n_steps and not last):
            return
        self._printed = step
        rate = (step - self._step0) / max(time.perf_counter() - (self._t0 or time.perf_counter()), 1e-9)
        shown = {k: v for k, v in self.get_metrics(trainer, pl_module).items() if k != "v_num"}
        figures = "".join(f"  {k} {v:.4g}" if isinstance(v, float) else f"  {k} {v}" for k, v in shown.items())
        print(
            f"step {step}/{total if total > 0 else '?'}{figures}  {rate:.2f} steps/s",
            file=self.stream or sys.stdout,
            flush=True,
        )


def progress_bar(enabled: bool = True, *, every_n_steps: int) -> ProgressBar | None:
    """The progress callback of a training run: None when ``trainer.enable_progress_bar`` is off (Lightning
    refuses a bar then), Lightning's bar on a terminal, :class:`LineProgress` otherwise."""
    if not enabled:
        return None
    return TQDMProgressBar() if is_terminal() else LineProgress(every_n_steps)
