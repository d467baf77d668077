"""A trial's outcome told to the study: its objective values (a value that is not a finite number fails the
trial), or how its job ended otherwise (pruned; pre-empted: queued again and the sweep stops; failed)."""

from __future__ import annotations

import logging
import math

import optuna
from omegaconf import OmegaConf
from optuna.trial import TrialState

from graf.errors import PREEMPTED_EXIT_CODE, is_preempted
from graf.sweeper.recovery import requeue
from graf.sweeper.trials import ERROR

log = logging.getLogger("graf")


class SweepPreempted(RuntimeError):
    """A trial was stopped by SIGTERM (a cluster pre-empting the job): its parameters are queued again (resuming
    from its checkpoint) and the sweep stops with the pre-emption's exit code; the same command resumes it."""

    exit_code = PREEMPTED_EXIT_CODE


def tell_values(study, trial, values, names: list[str], wall: float) -> None:
    """A completed job's objective values told; one not a finite number per objective is a failed trial."""
    values = list(values) if isinstance(values, (list, tuple)) or OmegaConf.is_list(values) else [values]
    try:
        values = [float(v) for v in values]
    except (TypeError, ValueError):
        values = [math.nan]
    if len(values) != len(names) or not all(math.isfinite(v) for v in values):
        trial.set_user_attr(ERROR, f"objective {names} returned {values}")
        study.tell(trial, state=TrialState.FAIL)
        log.warning("trial %d failed: its objective is %s (stored as failed; the study goes on)", trial.number, values)
    else:
        study.tell(trial, values)
        log.info("trial %d: %s = %s (%.1f s)", trial.number, names, values, wall)


def tell_failure(study, trial, ret) -> None:
    """A job that raised: pruned, pre-empted (queued again, and the sweep stops: :class:`SweepPreempted`), or
    failed."""
    exc = ret._return_value
    if isinstance(exc, optuna.TrialPruned):
        study.tell(trial, state=TrialState.PRUNED)
        log.info("trial %d pruned: %s", trial.number, exc)
    elif is_preempted(exc):
        has_cfg = getattr(ret, "hydra_cfg", None) is not None
        requeue(study, trial, str(ret.hydra_cfg.hydra.runtime.output_dir) if has_cfg else None)
        raise SweepPreempted(
            f"trial {trial.number} was pre-empted ({exc}); its parameters are queued again: "
            "run the same command to resume the search"
        )
    else:
        trial.set_user_attr(ERROR, f"{type(exc).__name__}: {exc}"[:2000])
        study.tell(trial, state=TrialState.FAIL)
        log.warning(
            "trial %d failed: %s: %s (stored as failed; the study goes on)", trial.number, type(exc).__name__, exc
        )
