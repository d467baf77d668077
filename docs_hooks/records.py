"""The Records page (``<!-- gen: records sweeps -->``): one entry per folder of ``sweeps/``, generated from the
folder when the site is built: its title (its README's first heading), what it holds (its runs, its tables, its
figures), the pages that cite it, and every figure it holds, each a thumbnail linked to the figure.

The figures are those the hooks publish (:func:`figures`): every ``*.png`` under ``sweeps/`` at any depth, but
those in a checkpoint's folder or a single Optuna trial's or model's folder.  A README's text is not copied (it
names machines and wall times, which the site keeps to the Reproducibility log); its title is, less a
parenthesis.
"""

from __future__ import annotations

import re
from pathlib import Path

SKIP = ("trial_", "model=", "checkpoints")  # folder names (prefixes) whose figures are not published
TABLES = (".md", ".json", ".csv")


def figures(folder: Path) -> list[Path]:
    """Every published figure under ``folder``, sorted."""
    return sorted(
        p for p in folder.rglob("*.png") if not any(part.startswith(SKIP) for part in p.relative_to(folder).parts[:-1])
    )


def title(folder: Path) -> str:
    """The README's first heading, less a parenthesis (where a README names its machine); the folder's name
    without a README."""
    readme = folder / "README.md"
    if readme.is_file():
        for line in readme.read_text().splitlines():
            if line.startswith("# "):
                return re.sub(r"\s*\([^)]*\)", "", line[2:]).strip(" ,:") or folder.name
    return folder.name


def holds(folder: Path) -> str:
    """What the folder holds, in one sentence: the kind of record, its runs, its top-level tables."""
    runs = [p for p in folder.rglob("results.json") if "checkpoints" not in p.parts]
    if (folder / "report.json").is_file():
        kind = f"A study: {len(runs)} jobs' results (`results.json`), the report (`report.json`)"
    elif (folder / "trials.csv").is_file():
        trials = len((folder / "trials.csv").read_text().strip().splitlines()) - 1
        kind = f"A hyperparameter search: {trials} trials (`trials.csv`), the chosen configuration's test (`best/`)"
    elif (folder / "curves.csv").is_file():
        points = len((folder / "curves.csv").read_text().strip().splitlines()) - 1
        kind = f"Learning curves: {points} points (`curves.csv`) from {len(runs)} runs"
    elif runs:
        kind = f"{len(runs)} run{'s' if len(runs) > 1 else ''}' results (`results.json`)"
    else:
        kind = "Records"
    tables = sorted(p.name for p in folder.iterdir() if p.suffix in TABLES and p.name not in ("README.md",))
    shown = [t for t in tables if t not in ("results.json", "report.json", "trials.csv", "curves.csv")]
    parts = [kind] + (
        [", ".join(f"`{t}`" for t in shown[:8]) + (" and more" if len(shown) > 8 else "")] if shown else []
    )
    readme = " Its `README.md` says how it was made." if (folder / "README.md").is_file() else ""
    return "; ".join(parts) + "." + readme


def cited(name: str, docs: Path, titles: dict[str, str]) -> list[str]:
    """Links to the pages of the navigation that name ``sweeps/<name>``."""
    pattern = re.compile(rf"sweeps/{re.escape(name)}(?![\w-])")
    out = []
    for path, page_title in titles.items():
        if path != "records.md" and (docs / path).is_file() and pattern.search((docs / path).read_text()):
            out.append(f"[{page_title}]({path})")
    return out


def entry(folder: Path, root: Path, titles: dict[str, str]) -> str:
    name = folder.name
    lines = [f"## {name}", ""]
    head = title(folder)
    lines += [(f"**{head}**. " if head != name else "") + f"`sweeps/{name}/`: " + holds(folder), ""]
    pages = cited(name, root / "docs", titles)
    if pages:
        lines += ["Cited on: " + ", ".join(pages) + ".", ""]
    figs = figures(folder)
    if figs:
        lines.append(f"{len(figs)} figure{'s' if len(figs) > 1 else ''} (each links to the figure at full size):")
        lines.append("")
        lines.append(
            " ".join(
                f"[![{p.relative_to(folder).as_posix()}]({_uri(p, root)}){{ .graf-thumb loading=lazy "
                f'title="{p.relative_to(folder).as_posix()}" }}]({_uri(p, root)})'
                for p in figs
            )
        )
        lines.append("")
    return "\n".join(lines)


def _uri(path: Path, root: Path) -> str:
    return path.relative_to(root).as_posix()


def page(sweeps: Path, root: Path, titles: dict[str, str]) -> str:
    """The Records page's generated part: an entry per folder of ``sweeps``, by name."""
    folders = sorted(p for p in sweeps.iterdir() if p.is_dir())
    total = sum(len(figures(f)) for f in folders)
    intro = f"{len(folders)} records, {total} figures; generated from `sweeps/` when this site is built."
    return "\n\n".join([intro, *[entry(f, root, titles) for f in folders]])


def nav_titles(nav: list, out: dict[str, str] | None = None) -> dict[str, str]:
    """The navigation's pages: path -> title, in order, at any depth."""
    out = {} if out is None else out
    for item in nav:
        if isinstance(item, dict):
            for key, value in item.items():
                if isinstance(value, str):
                    out[value] = key
                elif isinstance(value, list):
                    nav_titles(value, out)
    return out
