"""The errors that mean "what the user gave is wrong" (data, config values, checkpoints, files).

Every command ends on one of these with its message alone on stderr and exit code 2
(:func:`graf.cli.entry.cli_errors`); anything else is a bug and keeps its traceback.  The classes that
name a file (:class:`graf.data.spectrum_set.DataFormatError`), a checkpoint
(:class:`graf.models.base.CheckpointError`) or a neighbor shortage (:class:`graf.data.neighbors.NoNeighborsError`)
subclass :class:`UserError` beside :class:`ConfigError`.
"""

from __future__ import annotations

import collections.abc
import errno
import re
import types
import typing

from hydra.errors import InstantiationException
from hydra.utils import get_method
from omegaconf import OmegaConf
from omegaconf.errors import MissingMandatoryValue


class UserError(ValueError):
    """Something the user gave cannot be used as given; the message says what and where."""


class ConfigError(UserError):
    """A configuration that cannot run as given; the message says what to set."""


class PluginError(UserError):
    """A plugin's registered function (a metric, a study axis) failed or returned what graf cannot use; the message
    names it and its plugin module (:func:`graf.plugins.call_registered`)."""


class WriteError(UserError):
    """A file that cannot be written where the user asked (a full disk, a read-only folder); the message names it."""


DISK_FULL = ("No space left on device", "Disk quota exceeded")  # how a failed write says it when no errno is kept


def disk_full(exc: BaseException, folder=None) -> str | None:
    """A full disk (or quota) behind ``exc``, met by a writer that is not graf's own (a checkpoint's ``torch.save``,
    a logger's file): the line to end on, naming the run's output ``folder`` where given and the file being written
    where the error kept it (None: not a full disk).  Follows the exception's causes, since a library may wrap the
    OSError (torch's stream writer reports it as text)."""
    seen, where = set(), f" of {folder}" if folder else ""
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            writing = f", writing {exc.filename}" if exc.filename else ""
            return f"no space is left on the disk{where} ({exc.strerror}{writing}); the files written before are kept"
        if any(m in str(exc) for m in DISK_FULL):
            said = str(exc).strip()[:200]
            return f"no space is left on the disk{where} ({said}); the files written before are kept"
        exc = exc.__cause__ or exc.__context__
    return None


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
    (Hydra's instantiation error), and a full disk met by a writer that is not graf's own (:func:`disk_full`)."""

    return isinstance(exc, (UserError, MissingMandatoryValue, InstantiationException)) or disk_full(exc) is not None


def user_message(exc: BaseException, cfg=None) -> str:
    """A user error's message on one line: a constructor's own refusal rather than Hydra's three-line wrapper
    around it (``Error in call to target ...``), with the config node it came from.  Given the run's config, a
    setting of that node that is not of the type its constructor takes is named with its value
    (:func:`mistyped_setting`): ``neighbors.L=abc: must be an integer``, not ``invalid literal for int()``."""
    full = (
        None
        if isinstance(exc, UserError)
        else disk_full(
            exc,
            OmegaConf.select(cfg, "paths.output_dir", default=None, throw_on_resolution_failure=False)
            if cfg is not None
            else None,
        )
    )
    if full:
        return full

    cause = exc.__cause__ if isinstance(exc, InstantiationException) else None
    if cause is not None and str(cause):
        key = instantiated_key(exc)
        if cfg is not None and key and isinstance(cause, (TypeError, ValueError)) and not isinstance(cause, UserError):
            mistyped = mistyped_setting(cfg, key, said=str(cause))
            if mistyped:
                return mistyped
        return f"{cause}" + (f" (in {key})" if key and key not in str(cause) else "")
    return " ".join(str(exc).split("\n")) if "\n" in str(exc) else str(exc)


def instantiated_key(exc: BaseException) -> str | None:
    """The config node Hydra's instantiation error names (its ``full_key: ...`` line), or None."""
    for line in str(exc).splitlines():
        if line.startswith("full_key: "):
            return line[len("full_key: ") :].strip() or None
    return None


def mistyped_setting(cfg, key: str, said: str = "") -> str | None:
    """``<key>.<setting>=<value>: must be <type>`` for the first setting of the config node ``key`` whose value is
    not of the type its target's constructor is annotated with; None when every value fits, when nothing is known,
    or when the constructor's own message (``said``) names that setting, or names any setting of the node as
    ``model.<name>`` or ``<key>.<name>`` (its own refusal: a value it left for the run to fill in, such as
    KNN-DL's ``max_rank: null``, is no mistake of the user's)."""

    try:
        node = OmegaConf.to_container(OmegaConf.select(cfg, key), resolve=True)
        target = get_method(node["_target_"])
        hints = typing.get_type_hints(target.__init__ if isinstance(target, type) else target)
    except Exception:
        return None
    if any(re.search(rf"\b(model|{re.escape(key)})\.{re.escape(name)}\b", said) for name in node):
        return None  # the constructor's own refusal of one of its settings (model.lr=-1), whatever else is unfilled
    for name, value in node.items():
        hint = hints.get(name)
        if hint is not None and not fits(value, hint):
            if re.search(rf"\b{re.escape(name)}\b", said):
                return None
            return f"{key}.{name}={as_override(value)}: must be {describe(hint)}"
    return None


def as_override(value) -> str:
    """A value as written on the command line: ``[3, x]``, ``null``, ``true``."""
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(as_override(v) for v in value) + "]"
    if value is None:
        return "null"
    return str(value).lower() if isinstance(value, bool) else str(value)


def fits(value, hint) -> bool:
    """``value`` is of the annotated type ``hint`` (int, float, bool, str, None, unions, sequences of them);
    True for any other annotation."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(fits(value, a) for a in args)
    if origin in (list, tuple, collections.abc.Sequence):
        inner = [a for a in args if a is not Ellipsis]
        return isinstance(value, (list, tuple)) and (len(inner) != 1 or all(fits(v, inner[0]) for v in value))
    simple = {
        type(None): value is None,
        bool: isinstance(value, bool),
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, (int, float)) and not isinstance(value, bool),
        str: isinstance(value, str),
    }
    return simple.get(hint, True)


def describe(hint) -> str:
    """An annotation in words: ``int`` -> "an integer", ``float | None`` -> "a number or null"."""
    args = typing.get_args(hint)
    names = {type(None): "null", bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    plural = {bool: "booleans", int: "integers", float: "numbers", str: "strings"}
    if hint in names:
        return names[hint]
    if typing.get_origin(hint) in (list, tuple, collections.abc.Sequence):
        inner = [a for a in args if a is not Ellipsis]
        return f"a list of {plural.get(inner[0], 'values') if len(inner) == 1 else 'values'}"
    return " or ".join(describe(a) for a in args) if args else str(hint)
