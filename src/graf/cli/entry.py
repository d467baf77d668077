"""What every command shares: :func:`graf_command`, the one decorator of every command's ``main`` (where Hydra
finds the configs, the command line brought up to date and checked, and how a command ends on an error)."""

from __future__ import annotations

import functools
import sys

import hydra
from omegaconf import DictConfig

from graf.app.command import fail, full_error, in_multirun, record_job, run_multirun, users_environment
from graf.app.config import CONF_PATH, output_dir
from graf.app.overrides import check_overrides, modernize
from graf.console import filter_known_warnings
from graf.errors import ConfigError, is_user_error, user_message
from graf.interrupts import INTERRUPTED_EXIT_CODE, Terminated, ignore_further, install_sigterm, interrupted_line, stage

__all__ = ["CONF_PATH", "cli_errors", "graf_command"]


def cli_errors(main):
    """For a command's ``main`` (beneath ``@hydra.main``): a user error (:func:`is_user_error`) ends the command
    with its message alone on stderr and exit code 2, instead of a page of traceback; ``HYDRA_FULL_ERROR=1``
    shows the full traceback.  In a multirun each job's end is recorded (:func:`graf.app.command.record_job`)
    and its error raised as usual, so the sweep records the failed job and goes on with the others.  The
    understood third-party warnings are filtered first (:func:`graf.console.filter_known_warnings`)."""

    @functools.wraps(main)
    def wrapped(cfg: DictConfig, *args, **kwargs):
        filter_known_warnings()
        install_sigterm()
        multirun = in_multirun()
        try:
            with users_environment(), stage(str(cfg.get("task_name") or "the command")):
                result = main(cfg, *args, **kwargs)
        except KeyboardInterrupt as exc:  # said by graf_command, with the output folder unless its stage said more
            if not getattr(exc, "said", None):
                exc.said = interrupted_line(f"output folder: {output_dir(cfg)}")
            raise
        except Exception as exc:
            ctrl_c = getattr(exc, "exit_code", None) == INTERRUPTED_EXIT_CODE  # training stopped by Ctrl+C
            if multirun and not ctrl_c:  # (a Ctrl+C stops a multirun here: its next job would not start)
                record_job(cfg, exc)
                raise
            if hasattr(exc, "exit_code"):  # a run stopped on purpose (pre-emption, Ctrl+C): its own code
                if ctrl_c:
                    ignore_further()
                said = str(exc)
                if isinstance(exc, Terminated) and not exc.said_kept:
                    said += f"; output folder: {output_dir(cfg)}"
                print(said, file=sys.stderr)
                sys.exit(int(exc.exit_code))
            if not is_user_error(exc) or full_error():
                raise
            fail(user_message(exc, cfg))
        if multirun:
            record_job(cfg, None)
        return result

    return wrapped


def graf_command(config_name: str):
    """The decorator of every command's ``main``: Hydra's ``@hydra.main`` on the config ``config_name`` over
    :func:`cli_errors`.  Before Hydra reads the command line, old spellings are brought up to date with a warning
    (:func:`graf.app.overrides.modernize`) and the overrides Hydra would refuse with a page are refused with one
    line and exit code 2 (:func:`graf.app.overrides.check_overrides`); a multirun ends with its failed jobs
    counted (:func:`graf.app.command.run_multirun`); a Ctrl+C at any stage ends it with the line of that stage
    (:mod:`graf.interrupts`) and exit code 130.  ``HYDRA_FULL_ERROR=1`` leaves every error to Hydra, in full.
    Called with a composed config, ``main`` runs on it directly."""

    def decorate(main):
        hydra_main = hydra.main(version_base="1.3", config_path=CONF_PATH, config_name=config_name)(cli_errors(main))

        @functools.wraps(main)
        def command(cfg: DictConfig | None = None):
            try:
                return run_command(cfg)
            except KeyboardInterrupt as exc:  # at any stage: its line (graf.interrupts), exit code 130
                if full_error():
                    raise
                ignore_further()
                said = getattr(exc, "said", None) or interrupted_line("nothing was run: run the command again")
                print(said, file=sys.stderr)
                sys.exit(INTERRUPTED_EXIT_CODE)

        def run_command(cfg: DictConfig | None):
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
