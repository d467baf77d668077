"""How a command ends: a user error on one line with exit code 2 (:func:`fail`), and a multirun with one line per
failed job and how many of how many failed (:func:`record_job`, :func:`run_multirun`).  Used by the commands'
decorator, :func:`graf.cli.entry.graf_command`."""

from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.errors import ConfigCompositionException
from hydra.types import RunMode
from omegaconf import DictConfig

from graf.app.overrides import composition_error
from graf.errors import is_user_error, user_message

__all__ = ["JOBS", "JobOutcome", "fail", "full_error", "in_multirun", "record_job", "run_multirun", "users_environment"]

FULL_ERROR_HINT = "(HYDRA_FULL_ERROR=1 shows the full traceback)"
# During a multirun run_multirun sets HYDRA_FULL_ERROR=1 so that Hydra raises a failed job's error to it instead of
# printing a traceback; the user's own value waits here, and is what each job (and what it starts) sees.
USERS_FULL_ERROR = "GRAF_USERS_HYDRA_FULL_ERROR"


@dataclass
class JobOutcome:
    """How one job of a multirun ended: ``error`` is its one-line message (None: it finished)."""

    num: int
    overrides: str
    sweep_dir: str
    error: str | None = None
    user_error: bool = True
    exception: Exception | None = field(default=None, repr=False)


JOBS: list[JobOutcome] = []  # the jobs of this process's multirun, in the order they ended (record_job)


def full_error() -> bool:
    """The user asked for full tracebacks (``HYDRA_FULL_ERROR=1``)."""
    return os.environ.get(USERS_FULL_ERROR, os.environ.get("HYDRA_FULL_ERROR")) == "1"


def in_multirun() -> bool:
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def fail(message: str) -> None:
    """End the command on a user error: its message on one line, exit code 2."""
    print(f"error: {message}\n{FULL_ERROR_HINT}", file=sys.stderr)
    sys.exit(2)


def record_job(cfg: DictConfig, exc: Exception | None) -> None:
    """Add a multirun job's outcome to :data:`JOBS`; a failed one (not a pruned search trial, not a pre-emption)
    is printed on one line: its number, its overrides and its message."""
    if exc is not None and (type(exc).__name__ == "TrialPruned" or hasattr(exc, "exit_code")):
        return
    hc = HydraConfig.get()
    job = JobOutcome(int(hc.job.num), " ".join(hc.overrides.task), str(hc.sweep.dir))
    if exc is not None:
        job.exception, job.user_error = exc, is_user_error(exc)
        job.error = user_message(exc, cfg) if job.user_error else f"{type(exc).__name__}: {exc}".split("\n")[0]
        print(f"job {job.num} ({job.overrides}) failed: {job.error}", file=sys.stderr, flush=True)
    JOBS.append(job)


def set_full_error(value: str | None) -> None:
    """Set ``HYDRA_FULL_ERROR`` to ``value`` (unset for None or "")."""
    if value:
        os.environ["HYDRA_FULL_ERROR"] = value
    else:
        os.environ.pop("HYDRA_FULL_ERROR", None)


@contextlib.contextmanager
def users_environment():
    """A multirun job runs with the user's own ``HYDRA_FULL_ERROR`` (see :data:`USERS_FULL_ERROR`)."""
    ours = os.environ.get("HYDRA_FULL_ERROR")
    users = os.environ.get(USERS_FULL_ERROR)
    if users is not None:
        set_full_error(users)
    try:
        yield
    finally:
        if users is not None:
            set_full_error(ours)


class WithoutHydrasJobError:
    """sys.stderr without Hydra's ``Error executing job with overrides: [...]`` (written as the sweep raises its
    first failed job's error): every failed job has had its own line already (:func:`record_job`)."""

    def __init__(self, stream) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        return len(text) if text.startswith("Error executing job with overrides: ") else self.stream.write(text)

    def __getattr__(self, name: str):
        return getattr(self.stream, name)


def run_multirun(hydra_main, args: list[str]) -> None:
    """Run a multirun; when jobs failed, end with how many of how many (each was printed on one line when it
    failed) and exit code 2 when every failure was a user error, 1 otherwise."""
    JOBS.clear()
    os.environ[USERS_FULL_ERROR] = os.environ.get("HYDRA_FULL_ERROR", "")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        with contextlib.redirect_stderr(WithoutHydrasJobError(sys.stderr)):
            hydra_main()
    except Exception as exc:
        failed = [j for j in JOBS if j.error is not None]
        if failed:
            where = Path(failed[0].sweep_dir) / "failed.json"
            print(f"{len(failed)} of {len(JOBS)} jobs failed (listed in {where})", file=sys.stderr)
        if any(j.exception is exc for j in failed):
            sys.exit(2 if all(j.user_error for j in failed) else 1)
        # the sweep's own error (a job's config, a launcher, a search's max_failures): as a single run's
        if isinstance(exc, ConfigCompositionException):
            fail(user_message(composition_error(exc, args)))
        if is_user_error(exc):
            fail(user_message(exc))
        raise
    finally:
        set_full_error(os.environ.pop(USERS_FULL_ERROR))
