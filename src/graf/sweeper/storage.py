"""Where a study lives: the storage (an SQLite file, or an RDB shared across machines with Optuna's heartbeats),
the heartbeats a running trial's worker records there, and the lock that serialises the bookkeeping of processes
sharing an SQLite storage."""

from __future__ import annotations

import contextlib
import fcntl
import logging
import threading
import time
from pathlib import Path

import sqlalchemy.exc
from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback
from optuna.storages._heartbeat import is_heartbeat_enabled  # Optuna's own test, not exported by optuna.storages

log = logging.getLogger("graf")


@contextlib.contextmanager
def storage_lock(lock_path: Path | None):
    """An exclusive lock (fcntl) around the bookkeeping of processes sharing an SQLite storage."""
    if lock_path is None:
        yield
        return
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "a+") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def sqlite_path(url: str) -> Path | None:
    return Path(url[len("sqlite:///") :]) if url.startswith("sqlite:///") else None


def make_storage(url: str, heartbeat: dict | None):
    """The study's storage: the URL itself for SQLite (the owner check finds dead workers), an ``RDBStorage``
    with Optuna's heartbeats and retry callback for any other database."""
    if url.startswith("sqlite") or not heartbeat:
        if heartbeat and url.startswith("sqlite"):
            log.info(
                "storage %s is SQLite: hydra.sweeper.heartbeat (interval %s s, grace period %s s) is not used there; "
                "a dead worker's trial is found by its owner's host, pid and start time instead",
                url,
                heartbeat.get("interval"),
                heartbeat.get("grace_period"),
            )
        return url
    interval, grace = int(heartbeat["interval"]), heartbeat.get("grace_period")
    for attempt in range(5):
        try:
            return RDBStorage(
                url,
                heartbeat_interval=interval,
                grace_period=None if grace is None else int(grace),
                heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(max_retry=heartbeat["max_retry"]),
            )
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError) as exc:
            # workers starting together on an empty database race to create Optuna's tables (one wins, the
            # others' CREATE fails): the schema is there a moment later, so connect again
            if attempt == 4:
                raise
            log.info("the storage's schema is being created by another worker (%s): retrying", type(exc).__name__)
            time.sleep(0.5 + attempt)


def heartbeat_enabled(study) -> bool:
    """Whether the study's storage records heartbeats (an RDB storage made by :func:`make_storage`)."""
    return is_heartbeat_enabled(study._storage)


@contextlib.contextmanager
def heartbeats(study, trial):
    """Record ``trial``'s heartbeat every interval while the block runs (a thread of this worker), when the
    study's storage has heartbeats: the same records ``study.optimize`` makes, for this ask-and-tell loop."""
    if not heartbeat_enabled(study):
        yield
        return
    storage, stop = study._storage, threading.Event()
    interval = storage.get_heartbeat_interval()

    def beat() -> None:
        while True:
            with contextlib.suppress(Exception):  # a dropped connection: the next beat tries again
                storage.record_heartbeat(trial._trial_id)
            if stop.wait(interval):
                return

    t = threading.Thread(target=beat, name=f"heartbeat-trial-{trial.number}", daemon=True)
    t.start()
    try:
        yield
    finally:
        stop.set()
        t.join()
