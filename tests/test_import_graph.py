"""The package's import graph: no circle between modules, no import running up a floor, thin commands.

The graph is read from the source (every ``import`` and ``from ... import``, function-level ones included:
a lazy import is still a dependency), so it needs no heavy import and sees modules no test imports.

Floors, top to bottom (a module may import its own floor and those below, never one above; the rooms of one
floor do not import each other):

- ``graf.cli``: the commands, thin Hydra entry points (``cli.studies``, ``cli.case_studies``, ``cli.sim`` by kind);
- ``graf.studies`` (tools that run many runs: learning curves, Pareto fronts, benchmarks) and
  ``graf.case_studies`` (AoA, localization, interpolation, the oracle, synthesis);
- ``graf.reports``: reports over the records of many runs (graf-report, graf-table, graf-claims, the axes);
- ``graf.sweeper``: the Optuna sweeper, above the runs it drives;
- ``graf.run``: one run (building, training, evaluation, record);
- ``graf.search``: what a run of a search needs (objectives, pruning);
- everything else, the ground floor: the command framework (``graf.app``), data, models, metrics, geometry, the
  simulator and its tasks, plotting, callbacks, errors, io.

``hydra_plugins`` sits beside ``graf.cli`` (it only registers the sweeper with Hydra).

A study starts commands as a user would, in a subprocess, never by importing them: every such launch goes through
:func:`graf.app.launch.command` with the command's name (``command("graf-train", ...)``), which the graph reads as
an edge of its own kind (:func:`launches`); no other module names a command's module in a string.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
FLOORS = (
    ("graf.cli",),
    ("graf.studies", "graf.case_studies"),
    ("graf.reports",),
    ("graf.sweeper",),
    ("graf.run",),
    ("graf.search",),
)
# top first; anything else in graf is the ground floor
CLI_MAX_LINES = 110


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in SRC.rglob("*.py") if "conf" not in p.relative_to(SRC).parts}


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The module of ours that ``name`` (a module or a module's attribute) names, if any."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join(up + ([base] if base else []))
                targets = [f"{base}.{a.name}" for a in node.names] + [base]
            for t in targets:
                dep = _resolve(t, modules)
                if dep is not None and dep != mod and not mod.startswith(dep + "."):  # a package's own parents: no edge
                    graph[mod].add(dep)
    return graph


def floor(mod: str) -> int:
    """0 for the top floor (the commands); higher is lower."""
    if mod.startswith("hydra_plugins"):
        return 0
    for i, rooms in enumerate(FLOORS):
        if room(mod) in rooms:
            return i
    return len(FLOORS)


def room(mod: str) -> str:
    """The room (top-level package of graf, or module) a module lives in: ``graf.studies`` for
    ``graf.reports.study``."""
    return ".".join(mod.split(".")[:2])


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_graph_reader_sees_lazy_and_relative_imports():
    graph = import_graph()
    assert "graf.metrics.functional" in graph["graf.metrics"]  # relative: from .functional import ...
    assert "graf.run.train" in graph["graf.cli.train"]
    assert (
        floor("graf.cli.train")
        < floor("graf.reports.study")
        < floor("graf.run.build")
        < floor("graf.search.objectives")
    )
    assert floor("graf.search.objectives") < floor("graf.io")


def test_no_import_circle():
    assert cycles(import_graph()) == []


def test_no_import_runs_up_a_floor():
    graph = import_graph()
    upward = sorted(f"{m} -> {d}" for m, deps in graph.items() for d in deps if floor(d) < floor(m))
    assert upward == []


def test_rooms_of_one_floor_do_not_import_each_other():
    graph = import_graph()
    sideways = sorted(
        f"{m} -> {d}"
        for m, deps in graph.items()
        for d in deps
        if floor(d) == floor(m) < len(FLOORS) and room(d) != room(m)
    )
    assert sideways == []


@pytest.mark.parametrize("path", sorted((SRC / "graf" / "cli").rglob("*.py")), ids=lambda p: p.name)
def test_every_command_file_is_thin(path):
    n = len(path.read_text().splitlines())
    assert n <= CLI_MAX_LINES, f"{path.name}: {n} lines; its logic belongs in graf.run"


# --- sizes: small modules and small functions (issue: the house by stage) ---
MODULE_MAX_LINES = 400
FUNCTION_MAX_LINES = 60
# a module longer than the limit says why in its docstring (splitting it would cut one idea in two) and is named here
LONG_MODULES = {"graf.case_studies.interpolation"}


def test_no_module_is_over_the_size_limit():
    long = {
        mod: n
        for mod, path in _modules().items()
        if (n := len(path.read_text().splitlines())) > MODULE_MAX_LINES and mod not in LONG_MODULES
    }
    assert long == {}, f"modules over {MODULE_MAX_LINES} lines: {long}"


def test_no_function_is_over_the_size_limit():
    long = {}
    for mod, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > FUNCTION_MAX_LINES:
                    long[f"{mod}.{node.name}"] = n
    assert long == {}, f"functions over {FUNCTION_MAX_LINES} lines: {long}"


def test_no_private_name_is_imported_from_another_module():
    """A leading underscore says "this module's own": no other module of ours imports such a name."""
    modules = _modules()
    private = []
    for mod, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            ours = isinstance(node, ast.ImportFrom) and (
                node.level or (node.module or "").startswith(("graf", "hydra_"))
            )
            if ours:
                private += [
                    f"{mod}: from {node.module} import {a.name}"
                    for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")
                ]
    assert private == []


# --- launches: a study starts commands in a subprocess (graf.app.launch.command), never by importing them
LAUNCHERS = ("graf.studies", "graf.case_studies", "graf.reports")  # the rooms that may start commands


def launches() -> dict[str, set[str]]:
    """``{module: {command module}}``: every ``command("graf-...", ...)`` call of the package, read from the source
    and resolved through graf's console scripts (:func:`graf.app.launch.commands`)."""
    from graf.app.launch import module

    out: dict[str, set[str]] = {}
    for mod, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if not isinstance(node, ast.Call) or not node.args:
                continue
            name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
            first = node.args[0]
            if name == "command" and isinstance(first, ast.Constant) and str(first.value).startswith("graf-"):
                out.setdefault(mod, set()).add(module(first.value))
    return out


def test_the_graph_reader_sees_launches():
    found = launches()
    assert "graf.cli.train" in found["graf.studies.curves"]
    assert {"graf.cli.train", "graf.cli.evaluate", "graf.cli.sim.simulate"} <= found["graf.studies.pareto"]


def test_every_launch_goes_from_a_study_down_to_a_command():
    wrong = sorted(
        f"{m} -> {c}" for m, cs in launches().items() for c in cs if room(m) not in LAUNCHERS or room(c) != "graf.cli"
    )
    assert wrong == []


def test_no_module_starts_a_command_but_through_the_launcher():
    """A command's module named in a string (``"-m", "graf.cli.train"``) is a launch the graph cannot see."""
    import re

    named = []
    for mod, path in _modules().items():
        if mod == "graf.app.launch":
            continue
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                if re.fullmatch(r"graf\.cli(\.\w+)+", node.value):
                    named.append(f"{mod}: {node.value}")
    assert named == []


def test_only_the_sweeper_starts_its_own_command_again():
    """The one other launcher, :func:`graf.app.launch.again` (a search's further workers), is the sweeper's alone:
    :mod:`graf.sweeper.workers` calls it."""
    callers = set()
    for mod, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Call):
                name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
                if name == "again":
                    callers.add(mod)
    assert callers == {"graf.sweeper.workers"}


def test_the_launcher_knows_every_console_script():
    import re

    from graf.app.launch import commands

    section = (SRC.parent / "pyproject.toml").read_text().split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    scripts = dict(re.findall(r'^(graf-[\w-]+)\s*=\s*"([\w.]+):\w+"', section, re.M))
    assert commands() == scripts


ROOM_MAX_MODULES = 12  # modules of one folder of the package, its __init__ counted


def test_no_room_holds_more_than_twelve_modules():
    big = {
        str(d.relative_to(SRC)): n
        for d in sorted(p for p in (SRC / "graf").rglob("*") if p.is_dir() and "conf" not in p.parts)
        if (n := len(list(d.glob("*.py")))) > ROOM_MAX_MODULES
    }
    assert big == {}, f"folders of more than {ROOM_MAX_MODULES} modules: {big}"
