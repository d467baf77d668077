"""Plugins: your own metrics, study axes and methods, added without editing graf (docs/extending.md).

graf imports its plugins when it is first imported, before any command reads its registries:

- an installed package's entry points in the group ``graf.plugins`` (:data:`GROUP`; in its ``pyproject.toml``:
  ``[project.entry-points."graf.plugins"] mine = "my_plugin"``), the preferred way;
- ``GRAF_PLUGINS``: modules named in this environment variable (comma-separated, importable: a file on
  ``PYTHONPATH``, or installed).

A plugin module registers what it adds:

- a metric: :func:`graf.metrics.names.register` (name, label, unit, direction, per-spectrum function);
- a study axis: :func:`graf.reports.axes.register` (name, how it is read from a job's ``results.json``);
- a method: a :class:`graf.models.base.SpectrumModule` subclass (the :class:`graf.models.base.Method` interface)
  with its config ``model/<name>.yaml`` in the plugin's own conf folder, registered once with :func:`add_conf`:
  every graf command's Hydra search path then holds it (``hydra_plugins.graf_plugin_confs``), so ``model=<name>``
  works in graf-train, graf-eval and graf-bench as for graf's own methods.

A plugin that cannot be imported stops graf with one line naming it and its error, exit code 2
(``HYDRA_FULL_ERROR=1``: the traceback).  A registered function that raises (a metric's, a study axis's) stops
the command with one line naming what it computes and its plugin module (:func:`call_registered`).  The modules
loaded are :data:`LOADED`: a checkpoint of a plugin's method names a class of one of them
(:func:`graf.models.base.checkpoint_class`).
"""

from __future__ import annotations

import functools
import importlib
import os
import sys
from importlib.metadata import entry_points
from pathlib import Path

ENV = "GRAF_PLUGINS"
GROUP = "graf.plugins"  # the entry-point group of installed plugins
LOADED: list[str] = []  # the plugin modules imported, in order
CONF_DIRS: list[Path] = []  # the plugins' own conf folders (add_conf), searched after graf's own configs


def add_conf(folder) -> Path:
    """Register a plugin's own conf folder (``model/<name>.yaml`` and any other group), once, in the plugin
    module: every graf command then finds its configs (``hydra_plugins.graf_plugin_confs`` appends it to Hydra's
    search path, after graf's own, so a plugin adds options and never replaces one).  The folder, resolved."""
    path = Path(folder).resolve()
    if not path.is_dir():
        raise ValueError(f"graf.plugins.add_conf: {path} is not a folder (a plugin's conf folder: model/<name>.yaml)")
    if path not in CONF_DIRS:
        CONF_DIRS.append(path)
    return path


def entry_point_modules() -> list[str]:
    """The modules of the installed plugins (entry points of group :data:`GROUP`), in name order."""
    return [e.value.split(":")[0] for e in sorted(entry_points(group=GROUP), key=lambda e: e.name)]


def load_plugins(names: str | None = None) -> list[str]:
    """Import the modules of ``names`` (default: the installed plugins' entry points, then the ``GRAF_PLUGINS``
    environment variable); their names.  One that cannot be imported ends the process with one line naming it and
    where it was named, exit code 2 (graf is being imported: no command has started that could say it)."""
    if names is None:
        named = [(m, f"entry point of {GROUP}") for m in entry_point_modules()]
        named += [(m, ENV) for m in os.environ.get(ENV, "").split(",")]
    else:
        named = [(m, ENV) for m in names.split(",")]
    loaded = []
    for name, source in ((n.strip(), src) for n, src in named):
        if not name:
            continue
        try:
            importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001 - a plugin's own error, named with the plugin
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            print(
                f"error: {source}: plugin module {name!r} could not be imported: {type(exc).__name__}: "
                f"{one_line(exc)}\n(HYDRA_FULL_ERROR=1 shows the full traceback)",
                file=sys.stderr,
            )
            raise SystemExit(2) from None
        loaded.append(name)
        if name not in LOADED:
            LOADED.append(name)
    return loaded


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def is_plugin_module(module: str) -> bool:
    """``module`` is one of the plugins loaded (:data:`LOADED`) or a submodule of one."""
    return any(module == name or module.startswith(name + ".") for name in LOADED)


def plugin_of(fn) -> str | None:
    """The module a registered function comes from when it is not graf's own (a plugin's, a script's), or None."""
    while isinstance(fn, functools.partial):
        fn = fn.func
    module = getattr(fn, "__module__", None) or type(fn).__module__
    return None if module == "graf" or module.startswith("graf.") else module


def registered(what: str, fn) -> str:
    """``what`` with the plugin module of ``fn`` where it is not graf's: ``metric 'peak' (plugin module mine)``."""
    module = plugin_of(fn)
    return f"{what} (plugin module {module})" if module else what


def call_registered(what: str, fn, *args):
    """``fn(*args)``: a registered function (a metric's ``per_spectrum``, a study axis's reader).  When it is not
    graf's own (:func:`plugin_of`), an error it raises becomes one line naming ``what`` and its plugin module
    (:class:`graf.errors.PluginError`, exit code 2); graf's own keep their traceback (a bug of graf's)."""
    try:
        return fn(*args)
    except Exception as exc:
        from graf.errors import PluginError  # here: graf.errors imports Hydra, which graf's import does not need

        if plugin_of(fn) is None or isinstance(exc, PluginError):
            raise
        raise PluginError(f"{registered(what, fn)} failed: {type(exc).__name__}: {one_line(exc)}") from exc
