"""The errors that mean "what the user gave is wrong" (data, config values, checkpoints, files).

Every command ends on one of these with its message alone on stderr and exit code 2
(:func:`graf.cli.entry.cli_errors`); anything else is a bug and keeps its traceback.  The classes that
name a file (:class:`graf.data.spectrum_set.DataFormatError`), a checkpoint
(:class:`graf.models.base.CheckpointError`) or a neighbor shortage (:class:`graf.data.neighbors.NoNeighborsError`)
subclass :class:`UserError` beside :class:`ConfigError`.
"""

from __future__ import annotations


class UserError(ValueError):
    """Something the user gave cannot be used as given; the message says what and where."""


class ConfigError(UserError):
    """A configuration that cannot run as given; the message says what to set."""


PREEMPTED_EXIT_CODE = 143  # 128 + SIGTERM: what a shell reports for a job ended by SIGTERM


class Preempted(Exception):
    """A job stopped on purpose by SIGTERM with its state saved (graf-train's training, or a command that runs
    graf-train jobs one after another): the command exits with :attr:`exit_code`, and the same command resumes."""

    exit_code = PREEMPTED_EXIT_CODE


def is_preempted(exc: BaseException | None) -> bool:
    """A job stopped on purpose by SIGTERM (:class:`Preempted`, or anything carrying its exit code)."""
    return getattr(exc, "exit_code", None) == PREEMPTED_EXIT_CODE


def is_user_error(exc: BaseException) -> bool:
    """Errors in what the user gave (data, config values, checkpoints), whose message says what is wrong:
    :class:`graf.errors.UserError` (``ConfigError``, ``DataFormatError``, ``CheckpointError``,
    ``NoNeighborsError``), a mandatory config value left unset, and a constructor refusing a config value
    (Hydra's instantiation error)."""
    from hydra.errors import InstantiationException
    from omegaconf.errors import MissingMandatoryValue

    return isinstance(exc, (UserError, MissingMandatoryValue, InstantiationException))


def user_message(exc: BaseException) -> str:
    """A user error's message on one line: a constructor's own refusal rather than Hydra's three-line wrapper
    around it (``Error in call to target ...``), with the config node it came from."""
    from hydra.errors import InstantiationException

    cause = exc.__cause__ if isinstance(exc, InstantiationException) else None
    if cause is not None and str(cause):
        key = getattr(exc, "full_key", None)
        return f"{cause}" + (f" (in {key})" if key and str(key) not in str(cause) else "")
    return " ".join(str(exc).split("\n")) if "\n" in str(exc) else str(exc)
