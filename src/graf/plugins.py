"""Plugins: your own metrics, study axes and methods, added without editing graf (docs/extending.md).

``GRAF_PLUGINS`` names modules (comma-separated, importable: on ``PYTHONPATH`` or installed) that graf imports
when it is first imported, before any command reads its registries.  A plugin module registers what it adds:

- a metric: :func:`graf.metrics.names.register` (name, label, unit, direction, per-spectrum function);
- a study axis: :func:`graf.reports.axes.register` (name, how it is read from a job's ``results.json``);
- a method: a :class:`graf.models.base.SpectrumModule` subclass (the :class:`graf.models.base.Method` interface)
  with a config file in a folder given to Hydra (``hydra.searchpath=[file://DIR]``) as ``model/<name>.yaml``.

A plugin that cannot be imported stops graf with one line naming it.
"""

from __future__ import annotations

import importlib
import os

ENV = "GRAF_PLUGINS"


def load_plugins(names: str | None = None) -> list[str]:
    """Import the modules of ``names`` (default: the ``GRAF_PLUGINS`` environment variable); their names."""
    names = os.environ.get(ENV, "") if names is None else names
    loaded = []
    for name in (n.strip() for n in names.split(",")):
        if not name:
            continue
        try:
            importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001 - a plugin's own error, named with the plugin
            raise SystemExit(
                f"error: {ENV}: plugin {name!r} could not be imported: {type(exc).__name__}: {exc}"
            ) from None
        loaded.append(name)
    return loaded
