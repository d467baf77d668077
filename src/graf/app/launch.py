"""How a study starts a command: in a subprocess, by the command's name, as a user would (never by importing it).

    from graf.app.launch import command
    subprocess.run(command("graf-train", "experiment=graf_rfid_s23", "hydra.run.dir=out"))

:func:`command` turns a console script's name into ``[python, -m, its module, *args]`` (the interpreter that runs
graf, so a virtual environment need not be on ``PATH``), the modules read from graf's console scripts
(``pyproject.toml`` ``[project.scripts]``, the one list of them).  ``tests/test_import_graph.py`` reads every call
of it as a launch and checks that launches go from the studies down to the commands and nowhere else.  A search's
further workers run the search's own command again (:func:`again`), the one other launcher, called by the sweeper
alone.
"""

from __future__ import annotations

import functools
import re
import sys
from importlib.metadata import entry_points
from pathlib import Path

PYPROJECT = Path(__file__).resolve().parents[3] / "pyproject.toml"  # a checkout's (src/graf/app/launch.py)


@functools.lru_cache(maxsize=1)
def commands() -> dict[str, str]:
    """``{console script: module}`` of graf's commands (``graf-train`` -> ``graf.cli.train``): the installed
    package's entry points, or a checkout's ``pyproject.toml`` when graf runs from ``src/`` uninstalled."""
    found = {e.name: e.value.split(":")[0] for e in entry_points(group="console_scripts") if e.name.startswith("graf-")}
    if not found and PYPROJECT.is_file():  # [project.scripts]: name = "module:function" lines (no tomllib on 3.10)
        section = PYPROJECT.read_text().split("[project.scripts]", 1)[-1].split("\n[", 1)[0]
        found = dict(re.findall(r'^(graf-[\w-]+)\s*=\s*"([\w.]+):\w+"', section, re.M))
    return found


def module(name: str) -> str:
    """The module of the command ``name`` (``graf-train``); a ValueError naming the known ones otherwise."""
    known = commands()
    if name not in known:
        raise ValueError(f"no graf command {name!r}; the commands are {', '.join(sorted(known))}")
    return known[name]


def command(name: str, *args: str) -> list[str]:
    """The argument list that runs the command ``name`` with ``args`` in a subprocess."""
    return [sys.executable, "-m", module(name), *map(str, args)]


def again(*args: str) -> list[str]:
    """The argument list that runs this process's own command again with ``args`` (an Optuna search's further
    workers, :mod:`graf.sweeper.workers`): a graf command by its name (:func:`command`), run as
    ``python -m`` whether it was started as a console script or as a module; any other Hydra app (a test's) by its
    script.  ``tests/test_import_graph.py`` knows this launcher: only the sweeper calls it."""
    started = Path(sys.argv[0])
    file = started.as_posix()
    ours = (n for n, m in commands().items() if n == started.name or file.endswith(m.replace(".", "/") + ".py"))
    name = next(ours, None)
    return command(name, *args) if name else [sys.executable, str(started), *map(str, args)]
