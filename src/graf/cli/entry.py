"""What every command shares: where Hydra finds the configs, and how a command ends on an error."""

from __future__ import annotations

import functools
import os
import sys

from omegaconf import DictConfig

from graf.console import filter_known_warnings
from graf.errors import is_user_error, user_message
from graf.run.config import CONF_PATH

__all__ = ["CONF_PATH", "cli_errors"]


def cli_errors(main):
    """For a command's ``main`` (beneath ``@hydra.main``): a user error (:func:`is_user_error`) ends the command
    with its message alone on stderr and exit code 2, instead of a page of traceback; ``HYDRA_FULL_ERROR=1``
    shows the full traceback.  In a multirun the error is raised as usual, so the sweep records the failed
    job and goes on with the others.  The understood third-party warnings are filtered first
    (:func:`graf.console.filter_known_warnings`)."""

    @functools.wraps(main)
    def wrapped(cfg: DictConfig, *args, **kwargs):
        filter_known_warnings()
        try:
            return main(cfg, *args, **kwargs)
        except Exception as exc:
            from hydra.core.hydra_config import HydraConfig
            from hydra.types import RunMode

            multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
            if hasattr(exc, "exit_code") and not multirun:  # a run stopped on purpose (pre-emption): its own code
                print(str(exc), file=sys.stderr)
                sys.exit(int(exc.exit_code))
            if not is_user_error(exc) or multirun or os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            print(f"error: {user_message(exc)}\n(HYDRA_FULL_ERROR=1 shows the full traceback)", file=sys.stderr)
            sys.exit(2)

    return wrapped
