"""The site's pages made from the source tree, so they cannot drift from it: one API reference page per room of
the package (every public module, as a mkdocstrings ``::: graf.x.y`` block), the API index, and the layout
page's map (the floors of ``tests/test_import_graph.py``, each room with its modules, the console scripts of
``pyproject.toml``, the scripts of ``scripts/``).

A room is a top-level package of ``graf`` (``graf.run``) or a top-level module (``graf.errors``); it is
described by the first sentence of its docstring, each module by the first sentence of its own.  A public
module is any module of ``src/graf`` but the Hydra configs (``conf/``), a private ``_x.py`` and the console
scripts' entry files (their API is the command line: the Commands page).  Plain functions of the repository
root; no import of the package (the tree is read with ``ast``).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = "graf"
ROLE = re.compile(r":(?:mod|func|class|meth|attr|data|exc):`~?([^`]+)`")
SCRIPT = re.compile(r'^([\w-]+)\s*=\s*"([\w.:]+)"', re.M)  # graf-train = "graf.cli.train:main"
SENTENCE_END = re.compile(r"\.(?=\s|$)")
MODULE_ROOMS_PAGE = "modules"  # the page of the rooms that are single modules (graf.errors, graf.io, ...)


class TreeError(ValueError):
    """The tree cannot be described as it is (a module without a docstring)."""


def module_name(path: Path, src: Path) -> str:
    parts = list(path.relative_to(src).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules(root: Path, package: str = PACKAGE) -> dict[str, Path]:
    """Every module of ``src/<package>`` (packages included) but the configs, private ``_x.py`` files and those
    not shipped, by dotted name, sorted."""
    src = root / "src"
    found = {}
    for path in (src / package).rglob("*.py"):
        rel = path.relative_to(src).parts
        if "conf" in rel or any(p.startswith("_") and p != "__init__.py" for p in rel) or not shipped(path, src):
            continue
        found[module_name(path, src)] = path
    return dict(sorted(found.items()))


def shipped(path: Path, src: Path) -> bool:
    """In a regular package all the way up to its top-level name (``hydra_plugins`` itself is a namespace): a
    folder without ``__init__.py`` inside the package is unfinished work, and mkdocstrings cannot collect it."""
    top = src / path.relative_to(src).parts[0]
    return all((d / "__init__.py").is_file() for d in path.parents if top in d.parents)


def is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def summary(path: Path) -> str:
    """The first sentence of a module's docstring, as markdown (Sphinx roles as code, one line)."""
    doc = ast.get_docstring(ast.parse(path.read_text(), filename=str(path)))
    if not doc:
        raise TreeError(f"{path}: no docstring; the site describes every module by its docstring's first sentence")
    paragraph = " ".join(doc.split("\n\n")[0].split())
    end = SENTENCE_END.search(paragraph)
    sentence = paragraph[: end.end()] if end else paragraph
    return ROLE.sub(r"`\1`", sentence).replace("``", "`").replace("|", "\\|")


def room(mod: str) -> str:
    """``graf.reports`` for ``graf.reports.study``; a top-level module is its own room."""
    return ".".join(mod.split(".")[:2])


def floors(root: Path) -> tuple[tuple[str, ...], ...]:
    """The floors above the ground floor, top first: ``FLOORS`` of ``tests/test_import_graph.py``."""
    path = root / "tests" / "test_import_graph.py"
    for node in ast.parse(path.read_text(), filename=str(path)).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "FLOORS" for t in node.targets):
            return ast.literal_eval(node.value)
    raise TreeError(f"{path}: no FLOORS")


def commands(root: Path) -> dict[str, str]:
    """The console scripts of ``pyproject.toml``: name -> entry module."""
    text = (root / "pyproject.toml").read_text()  # read by hand: tomllib is Python 3.11+, the package 3.10+
    section = text.partition("\n[project.scripts]\n")[2].split("\n[", 1)[0]
    entries = dict(SCRIPT.findall(section))
    if not entries:
        raise TreeError(f"{root / 'pyproject.toml'}: no [project.scripts]")
    return {name: target.partition(":")[0] for name, target in entries.items()}


def rooms(root: Path) -> dict[str, list[str]]:
    """Room -> its modules (the room's package first), rooms ordered by floor, top first, then by name (on the
    ground floor, packages before single modules)."""
    by_room: dict[str, list[str]] = {}
    for mod in modules(root):
        by_room.setdefault(room(mod), []).append(mod)
    upper = [r for floor in floors(root) for r in floor]
    order = {r: i for i, r in enumerate(upper)}
    mods = modules(root)
    ground = sorted((r for r in by_room if r not in order and r != PACKAGE), key=lambda r: (not is_package(mods[r]), r))
    return {r: by_room[r] for r in [PACKAGE, *sorted(order, key=order.get), *ground] if r in by_room}


def api_modules(root: Path) -> list[str]:
    """The modules that get a ``:::`` block: every public module but packages (their docstring opens their
    room's page; their names are re-exports) and the console scripts' entry files."""
    entries = set(commands(root).values())
    return [m for m, p in modules(root).items() if not is_package(p) and m not in entries]


def api_page(r: str, path: Path) -> str:
    """The page (``api/run.md``) of room ``r`` (its module or package at ``path``)."""
    return f"api/{r.split('.')[1]}.md" if is_package(path) else f"api/{MODULE_ROOMS_PAGE}.md"


def doc_text(path: Path) -> str:
    """A package's docstring as markdown (Sphinx roles as code), for the top of its page."""
    doc = ast.get_docstring(ast.parse(path.read_text(), filename=str(path))) or ""
    return ROLE.sub(r"`\1`", doc).replace("``", "`").replace("::\n\n", ":\n\n")


def room_lines(r: str, members: list[str], root: Path) -> list[str]:
    """A room on its API page: a package's title and docstring, then a ``:::`` block per public module."""
    path, listed = modules(root)[r], set(api_modules(root))
    lines = [f"# `{r}`", "", doc_text(path), ""] if is_package(path) else [""]
    if r == f"{PACKAGE}.cli":
        lines += ["The entry files of the console scripts are the commands: see [Commands](../commands.md).", ""]
    return lines + [f"::: {m}" for m in members if m in listed] + [""]


def api_pages(root: Path) -> dict[str, tuple[str, str]]:
    """Page path (``api/run.md``) -> (its title in the navigation, its markdown), in navigation order, the
    index first; the rooms that are one module share a page."""
    mods = modules(root)
    singles = f"api/{MODULE_ROOMS_PAGE}.md"
    index = ["# API reference", "", "One page per room of the package, generated from the source tree when the "
             "site is built; [Layout](../layout.md) has the floors, the modules and the commands.", "",
             "| room | what it is |", "|---|---|"]  # fmt: skip
    pages: dict[str, tuple[str, list[str]]] = {}
    for r, members in rooms(root).items():
        if r == PACKAGE:
            continue
        page = api_page(r, mods[r])
        title = "Top-level modules" if page == singles else r
        pages.setdefault(page, (title, [f"# {title}", ""] if page == singles else []))[1].extend(
            room_lines(r, members, root)
        )
        index.append(f"| [`{r}`]({page.removeprefix('api/')}) | {summary(mods[r])} |")
    out = {"api/index.md": ("Overview", "\n".join(index) + "\n")}
    out.update({page: (title, "\n".join(lines) + "\n") for page, (title, lines) in pages.items()})
    return out


def table(header: list[str], body: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *["| " + " | ".join(r) + " |" for r in body]]


def floor_lines(root: Path) -> list[str]:
    """The floors, top first, with their rooms."""
    upper = floors(root)
    ground = [r for r in rooms(root) if r != PACKAGE and not any(r in f for f in upper)]
    body = [[str(i + 1), ", ".join(f"`{r}`" for r in f)] for i, f in enumerate(upper)]
    body.append(["ground", ", ".join(f"`{r}`" for r in ground)])
    return [
        "## Floors",
        "",
        "A module imports its own floor and those below, never one above, and the rooms of one floor do not import "
        "each other (`tests/test_import_graph.py`, whose `FLOORS` this table is; `hydra_plugins` sits beside "
        "`graf.cli`).",
        "",
        *table(["floor (top first)", "rooms"], body),
        "",
    ]


def module_table(mods: dict[str, Path], skip: set[str] = frozenset()) -> list[str]:
    return table(["module", "what it is"], [[f"`{m}`", summary(p)] for m, p in mods.items() if m not in skip])


def room_sections(root: Path) -> list[str]:
    """Each room of the package in one line, with its modules (the commands' entry files are in the commands'
    table); then ``hydra_plugins``."""
    mods, entries = modules(root), set(commands(root).values())
    lines = ["## Rooms and their modules", "", f"`{PACKAGE}`: {summary(mods[PACKAGE])}", ""]
    for r, members in rooms(root).items():
        if r == PACKAGE:
            continue
        lines += [f"### `{r}`", "", summary(mods[r]), ""]
        if is_package(mods[r]):
            lines += [*module_table({m: mods[m] for m in members}, skip={r, *entries}), ""]
    plugins = modules(root, "hydra_plugins")
    return lines + [
        "### `hydra_plugins`",
        "",
        "Hydra finds graf's sweeper plugin here.",
        "",
        *module_table(plugins),
        "",
    ]


def command_lines(root: Path) -> list[str]:
    """The console scripts of ``pyproject.toml``, with their entry files and what they do."""
    mods = modules(root)
    body = [[f"`{name}`", f"`{entry}`", summary(mods[entry])] for name, entry in commands(root).items()]
    return ["## Commands", "", "The console scripts (`pyproject.toml`; options on [Commands](commands.md)).", "",
            *table(["command", "entry file", "what it does"], body), ""]  # fmt: skip


def script_lines(root: Path) -> list[str]:
    """The Python scripts of ``scripts/``, with their docstrings' first sentences."""
    body = [[f"`scripts/{p.name}`", summary(p)] for p in sorted((root / "scripts").glob("*.py"))]
    return ["## Scripts", "", *table(["script", "what it does"], body), ""]


def layout(root: Path) -> str:
    """The layout page's map: floors, rooms with their modules, commands, scripts."""
    return "\n".join(floor_lines(root) + room_sections(root) + command_lines(root) + script_lines(root))
