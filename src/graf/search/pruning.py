"""Pruning a hopeless trial from the validation metric logged during training.

A small Lightning callback (Lightning 2.6; Optuna's own integration lives in the separate
``optuna-integration`` package, not installed here): after each validation during training it reports
``monitor`` at the global step to the trial (``trial.report``), and raises :class:`optuna.TrialPruned`
when the study's pruner says so; never at the validation that ends training (``max_steps`` reached:
pruning then would discard a finished trial and save nothing).  Lightning tears the fit down and re-raises it; Hydra's
launcher returns
it as the job's failure, and the sweeper stores the trial as PRUNED (with its reported values).

The ``callbacks`` group makes it (``callbacks.optuna_pruning: {_target_: graf.search.pruning.pruning_callback,
conf: ${optuna_trial}}``; nothing for a run that is no trial).  The trial is reopened from the study's storage in the
job (``optuna_trial: {storage, study_name,
trial_id, monitor, pruner}``, set by the sweeper, with the sweeper's pruner settings), so it works in-process and in a
launcher's separate processes.
Validation during training must be on (``trainer.limit_val_batches`` > 0, ``trainer.val_check_interval``):
the searches in ``conf/hparams_search`` turn it on.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

from lightning.pytorch.callbacks import Callback

if TYPE_CHECKING:
    import optuna

log = logging.getLogger("graf")


class OptunaPruning(Callback):
    """Reports ``monitor`` to the Optuna ``trial`` after each validation and stops the run when the trial's pruner
    says so (validation during training must be on)."""

    def __init__(self, trial: optuna.trial.Trial, monitor: str = "val/psnr"):
        self.trial, self.monitor = trial, monitor
        self.reported: list[tuple[int, float]] = []
        self._warned = False

    def on_validation_end(self, trainer, pl_module) -> None:
        if trainer.sanity_checking:
            return
        value = trainer.callback_metrics.get(self.monitor)
        if value is None:
            if not self._warned:
                log.warning(
                    "pruning: %s was not logged by the validation during training; nothing reported", self.monitor
                )
                self._warned = True
            return
        value, step = float(value), int(trainer.global_step)
        import optuna  # lazy: a run that is no trial (the callback is None) never needs Optuna installed

        if not math.isfinite(value):  # the synced metric: every rank of a data-parallel run stops together
            raise optuna.TrialPruned(f"{self.monitor} is {value} at step {step}")
        # rank 0 reports and asks the pruner; the other ranks of a data-parallel run take its decision, so that
        # they all stop (or all go on) at the same step
        prune = False
        if trainer.is_global_zero:
            self.trial.report(value, step)
            prune = not is_last_validation(trainer) and self.trial.should_prune()
        self.reported.append((step, value))
        if trainer.world_size > 1:
            prune = bool(trainer.strategy.broadcast(prune, src=0))
        if prune:  # never at the validation that ends training: the objective decides, pruning would waste it
            raise optuna.TrialPruned(f"trial {self.trial.number} pruned at step {step}: {self.monitor}={value:.4f}")


def is_last_validation(trainer) -> bool:
    """The validation at the end of training (the step budget reached): nothing is left to save."""
    max_steps = int(getattr(trainer, "max_steps", -1) or -1)
    return max_steps > 0 and int(trainer.global_step) >= max_steps


def pruning_callback(conf) -> OptunaPruning | None:
    """The callback of a trial (``conf``: ``optuna_trial`` of the run's config), or None for a run that is no
    trial (``conf`` null), a multi-objective study (Optuna does not prune those) or when pruning is off
    (``monitor: null``).  The ``callbacks`` group composes it (``callbacks.optuna_pruning``)."""
    if not conf or not conf.get("monitor"):
        return None
    import optuna  # lazy: only a trial's run needs Optuna (a GPU machine without it runs everything else)

    from graf.search.pruners import make_pruner

    pruner = make_pruner(dict(conf.get("pruner") or {"name": "median"}))  # the sweeper's: the job decides with it
    study = optuna.load_study(study_name=str(conf.study_name), storage=str(conf.storage), pruner=pruner)
    if len(study.directions) > 1:
        return None
    return OptunaPruning(optuna.trial.Trial(study, int(conf.trial_id)), str(conf.monitor))
