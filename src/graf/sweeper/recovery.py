"""Trials that did not end by their own fault: those whose worker died (found by its owner, or by Optuna's
heartbeats on a shared storage) are failed and their parameters queued again, resuming from their last checkpoint;
a trial whose parameters a finished trial had takes that trial's outcome instead of training again."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from optuna.storages import fail_stale_trials
from optuna.trial import FrozenTrial, TrialState

from graf.sweeper.storage import heartbeat_enabled
from graf.sweeper.trials import DUPLICATE, INTERRUPTED, OUTPUT, OWNER, POLL_S, REQUEUED, RESUME, retried
from graf.sweeper.workers import owner_alive

log = logging.getLogger("graf")


def recover_interrupted(study, heartbeat: dict) -> None:
    """Trials left RUNNING by a worker that is gone, failed and queued again: found by Optuna's heartbeats on a
    shared RDB storage (``heartbeat``: its interval and grace period, for the message), by the owner's host, pid
    and start time on SQLite."""
    if heartbeat_enabled(study):  # a shared RDB storage: Optuna's heartbeats find dead workers on any machine
        before = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
        fail_stale_trials(study)
        trials = study.get_trials(deepcopy=False)
        for n in sorted(before & retried(trials)):
            log.warning(
                "trial %d: its worker %s sent no heartbeat for %s s: failed and queued again by Optuna",
                n,
                trials[n].user_attrs.get(OWNER),
                heartbeat.get("grace_period") or 2 * int(heartbeat["interval"]),
            )
        return
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        owner = t.user_attrs.get(OWNER)
        alive = owner_alive(owner)
        if alive or alive is None:
            continue
        if owner is None and t.datetime_start and (time.time() - t.datetime_start.timestamp()) < 60:
            continue  # just asked by another process, its owner not written yet
        log.warning("trial %d: its process %s is gone", t.number, owner)
        try:
            requeue(study, t, t.user_attrs.get(OUTPUT))
        except Exception:  # finished meanwhile, or recovered by another process
            continue


def requeue(study, trial, output_dir: str | None) -> None:
    """A trial that did not end by its own fault (its process killed, or pre-empted): stored as failed but
    not counted as the configuration's failure, and its parameters queued again, resuming from its last
    checkpoint when it has one."""
    storage = study._storage
    storage.set_trial_user_attr(trial._trial_id, INTERRUPTED, True)
    storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
    attrs = {REQUEUED: trial.number}
    ckpt = Path(output_dir) / "checkpoints" / "last.ckpt" if output_dir else None
    if ckpt is not None and ckpt.is_file():
        attrs[RESUME] = str(ckpt)
    study.enqueue_trial(trial.params, user_attrs=attrs)
    log.warning(
        "trial %d was interrupted: stored as failed, its parameters queued again%s",
        trial.number,
        f" (resuming from {ckpt})" if RESUME in attrs else "",
    )


def took_duplicate(study, trial) -> bool:
    """Whether a finished trial had the same parameters: its outcome is then told for this one."""
    dup = _duplicate(study, trial)
    if dup is None:
        return False
    trial.set_user_attr(DUPLICATE, dup.number)
    if dup.state == TrialState.COMPLETE:
        study.tell(trial, dup.values)
    else:
        study.tell(trial, state=TrialState.PRUNED)
    log.info(
        "trial %d: the parameters of trial %d (%s): its outcome taken, nothing trained",
        trial.number,
        dup.number,
        dup.state.name,
    )
    return True


def _duplicate(study, trial) -> FrozenTrial | None:
    """A finished or running trial (not this one) with the same parameters, once it has finished."""
    while True:
        same = [
            t
            for t in study.get_trials(deepcopy=False)
            if t.number != trial.number
            and t.params == trial.params
            and (
                t.state in (TrialState.COMPLETE, TrialState.PRUNED)
                or (t.state == TrialState.RUNNING and OWNER in t.user_attrs)
            )
        ]
        if not same:
            return None
        done = [t for t in same if t.state != TrialState.RUNNING]
        if done:
            return done[0]
        time.sleep(POLL_S)  # the same configuration is being trained elsewhere: take its outcome
