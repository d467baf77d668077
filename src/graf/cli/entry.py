"""What every command shares: :func:`graf_command`, the one decorator of every command's ``main`` (where Hydra
finds the configs, the command line brought up to date and checked, and how a command ends on an error)."""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import ConfigCompositionException
from hydra.types import RunMode
from omegaconf import DictConfig

from graf.cli.overrides import check_overrides, composition_error, modernize
from graf.console import filter_known_warnings
from graf.errors import ConfigError, is_user_error, user_message
from graf.run.config import CONF_PATH

__all__ = ["CONF_PATH", "JOBS", "cli_errors", "graf_command"]

FULL_ERROR_HINT = "(HYDRA_FULL_ERROR=1 shows the full traceback)"
# During a multirun graf_command sets HYDRA_FULL_ERROR=1 so that Hydra raises a failed job's error to it instead of
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


JOBS: list[JobOutcome] = []  # the jobs of this process's multirun, in the order they ended (cli_errors)


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
        job.user_error = is_user_error(exc)
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


def cli_errors(main):
    """For a command's ``main`` (beneath ``@hydra.main``): a user error (:func:`is_user_error`) ends the command
    with its message alone on stderr and exit code 2, instead of a page of traceback; ``HYDRA_FULL_ERROR=1``
    shows the full traceback.  In a multirun each job's end is recorded (:func:`record_job`) and its error raised
    as usual, so the sweep records the failed job and goes on with the others.  The understood third-party
    warnings are filtered first (:func:`graf.console.filter_known_warnings`)."""

    @functools.wraps(main)
    def wrapped(cfg: DictConfig, *args, **kwargs):
        filter_known_warnings()
        multirun = in_multirun()
        try:
            with users_environment():
                result = main(cfg, *args, **kwargs)
        except Exception as exc:
            if multirun:
                record_job(cfg, exc)
                raise
            if hasattr(exc, "exit_code"):  # a run stopped on purpose (pre-emption): its own code
                print(str(exc), file=sys.stderr)
                sys.exit(int(exc.exit_code))
            if not is_user_error(exc) or full_error():
                raise
            fail(user_message(exc, cfg))
        if multirun:
            record_job(cfg, None)
        return result

    return wrapped


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
        if not failed:  # not a job's own error (a job's config, a launcher): reported as a single run's
            if isinstance(exc, ConfigCompositionException):
                fail(user_message(composition_error(exc, args)))
            if is_user_error(exc):
                fail(user_message(exc))
            raise
        where = Path(failed[0].sweep_dir) / "failed.json"
        print(f"{len(failed)} of {len(JOBS)} jobs failed (listed in {where})", file=sys.stderr)
        sys.exit(2 if all(j.user_error for j in failed) else 1)
    finally:
        set_full_error(os.environ.pop(USERS_FULL_ERROR))


def graf_command(config_name: str):
    """The decorator of every command's ``main``: Hydra's ``@hydra.main`` on the config ``config_name`` over
    :func:`cli_errors`.  Before Hydra reads the command line, old spellings are brought up to date with a warning
    (:func:`graf.cli.overrides.modernize`) and the overrides Hydra would refuse with a page are refused with one
    line and exit code 2 (:func:`graf.cli.overrides.check_overrides`); a multirun ends with its failed jobs
    counted (:func:`run_multirun`).  ``HYDRA_FULL_ERROR=1`` leaves every error to Hydra, in full.  Called with a
    composed config, ``main`` runs on it directly."""

    def decorate(main):
        hydra_main = hydra.main(version_base="1.3", config_path=CONF_PATH, config_name=config_name)(cli_errors(main))

        @functools.wraps(main)
        def command(cfg: DictConfig | None = None):
            if cfg is not None:
                return hydra_main(cfg)
            sys.argv[1:], warnings = modernize(sys.argv[1:])
            for line in warnings:
                print(line, file=sys.stderr)
            if full_error():
                return hydra_main()
            args = [a for a in sys.argv[1:] if a not in ("-m", "--multirun")]
            if not any(a.startswith("-") for a in args):  # other flags (--cfg, -cn, --help): Hydra's alone
                try:
                    check_overrides(config_name, args)
                except ConfigError as exc:
                    fail(str(exc))
            if len(args) < len(sys.argv) - 1:
                return run_multirun(hydra_main, args)
            return hydra_main()

        return command

    return decorate
