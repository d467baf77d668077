"""The check that every figure a markdown file states is held by its record: a study record's README by the
folder's files, a site page (and the repository's README) by the records of ``sweeps/`` it names.

:func:`not_held` reads the figures a markdown file states and names those its record does not hold
(:func:`readme_problems` for a record's README, :func:`pages_problems` for the site's pages).  Run by
``tests/reports/test_stated_figures.py`` over every record and page.
"""

from __future__ import annotations

import bisect
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

FIGURE = re.compile(
    r"(?<![\w.])(?P<sign>[-+−])?(?P<int>\d+)(?P<frac>\.\d+)?(?P<exp>[eE][-+−]\d+)?(?P<pct>%)?(?P<tail>[\w.]*)"
)
UNIT = re.compile(  # after a figure, across a range or list of figures ("0.40-0.45 s", "0.38 and 0.43 s/step")
    r"(?:\s*(?:-|–|->|to|and|or|/|,)\s*[-+−]?\d[\d,]*(?:\.\d+)?)*\s*"
    r"(?:ms|s|sec|seconds?|min|minutes?|h|hours?|days?|UTC|[kMG]?Hz|mm|cm|km|m|wavelengths?|[KMGT]i?B)(?!\w)"
)
BEFORE = re.compile(r"(?:(?:version|python|arxiv)\s*:?\s*|[\w\]]=|\d\s*x\s*)$", re.I)  # a label, an override, a size
AFTER = re.compile(r"\s*x\s*\d|\s+(?:bootstrap\s+)?interval")  # a size's first side (7.2 x 6); a confidence level
NAMED = re.compile(r"sweeps/([\w-]+)|<!-- gen: (?:study|search) ([\w-]+) -->|records\.md#([\w-]+)")
RECORD_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
RECORD_SUFFIXES = (".json", ".csv", ".md", ".txt", ".tex")
SUPPLEMENT = Path("shared/seed/graf_supplementary.txt")  # beside the repository: ../shared


@dataclass
class Held:
    """The numbers a record holds (sorted) and the number tokens of the paper's text."""

    values: list[float] = field(default_factory=list)
    paper: set[str] = field(default_factory=set)

    def holds(self, value: float, half: float, signed: bool) -> bool:
        """Whether a record number rounds to ``value`` within ``half`` (an unsigned figure: either sign)."""
        for v in (value,) if signed else (value, -value):
            i = bisect.bisect_left(self.values, v - half * (1 + 1e-9))
            if i < len(self.values) and self.values[i] <= v + half * (1 + 1e-9):
                return True
        return False


def record_numbers(folder: Path, paper: Path | None = None) -> Held:
    """Every number in the record files under ``folder`` (json, csv, md, txt, tex; its README.md left out), and
    the number tokens of the text ``paper`` when given."""
    values = []
    for f in sorted(folder.rglob("*")):
        if f.suffix in RECORD_SUFFIXES and f.name != "README.md" and f.is_file():
            values += [float(x) for x in RECORD_NUMBER.findall(f.read_text(errors="replace"))]
    return Held(sorted(v for v in values if math.isfinite(v)), paper_tokens(paper))


def paper_tokens(paper: Path | None) -> set[str]:
    """The number tokens of the paper's text ``paper`` (none when None)."""
    return set(re.findall(r"\d+(?:\.\d+)?", paper.read_text())) if paper else set()


def prose(text: str) -> list[tuple[int, str]]:
    """``text``'s lines (numbered from 1) with what states no figure blanked: code blocks (fenced, and indented
    after a blank line), generated blocks (``<!-- NAME: generated ... -->`` to ``<!-- /NAME -->``), HTML comments
    (the site's ``<!-- gen: ... -->`` directives), inline code, link targets and web addresses."""
    out, fence, generated, comment, prev_blank, code = [], None, None, False, True, False
    for n, line in enumerate(text.split("\n"), 1):
        stripped = line.strip()
        if fence or generated or comment:
            fence = None if fence and stripped.startswith(fence) else fence
            generated = None if generated and stripped.startswith(f"<!-- /{generated} -->") else generated
            comment = comment and "-->" not in line
            continue
        if stripped.startswith(("```", "~~~")):
            fence = stripped[:3]
            continue
        m = re.match(r"<!-- ([\w-]+): generated", stripped)
        if m:
            generated = m.group(1)
            continue
        code = line.startswith(("    ", "\t")) and (prev_blank or code)
        prev_blank = not stripped
        if code:
            continue
        line = re.sub(r"<!--.*?(-->|$)", " ", line)
        comment = "<!--" in line
        line = re.sub(r"`[^`]*`|\]\([^)]*\)|https?://\S+", " ", line)
        out.append((n, line))
    return out


def figures(line: str, follow: str = "") -> list[tuple[str, float, float, bool, bool]]:
    """The figures ``line`` states: (as written, value, half its last digit, signed, a percentage); ``follow``,
    the next line, may hold a figure's unit or what makes it a setting."""
    out, joined = [], f"{line} {follow.strip()}"
    for m in FIGURE.finditer(line):
        tail = m["tail"].rstrip(".")
        skip = not (m["frac"] or m["pct"]) or m["exp"] or tail not in ("", "x") or BEFORE.search(line, 0, m.start())
        if skip or UNIT.match(joined, m.end()) or AFTER.match(joined, m.end()):
            continue
        digits = len(m["frac"] or ".") - 1
        value = float(m["int"] + (m["frac"] or "")) * (-1 if m["sign"] in ("-", "−") else 1)
        out.append((m.group(0).rstrip("."), value, 0.5 * 10.0**-digits, bool(m["sign"]), bool(m["pct"])))
    return out


def not_held(text: str, held: Held, name: str = "") -> list[str]:
    """The figures stated in ``text`` (markdown) that ``held`` does not hold, one line each: ``name:line: figure``.

    A figure is a number with a decimal point (``22.31``, ``+0.43``, each end of ``[-0.15, +0.11]``, ``0.832``,
    ``3.2x``) or a percentage (``57%``); it is held when a number of the record rounds to it at the precision it
    is written with (a figure written without a sign: either sign, as in "lower by 0.003"; a percentage: the
    number or its hundredth), or when it is written as it is in the paper's text.  Not read (the exemptions,
    settings, sizes and labels, not results):

    - what :func:`prose` blanks: code, generated blocks, comments, inline code (a setting's value, a constant, a
      published reference value a test asserts: ``d(ex_ref, ex_p0) = 0.722``), link targets;
    - a number in scientific notation (``1e-3``, ``4e-7``: learning rates, floors, tolerances), or glued to a
      setting's name by ``=`` (``lr=0.0005``: an override);
    - a side of a size written ``a x b [x c]`` (``7.2 x 14.9 x 6.2``);
    - a percentage before "interval" or "bootstrap interval" (``95% interval``: the confidence level);
    - a number glued to a word (``1.8ghz``, ``v1.2``) or one of a dotted version (``2.4.1``), or after "version",
      "Python" or "arXiv";
    - a figure followed, alone or as the end of a range or list, by a unit of time, frequency, length or size
      (``0.44 s/step``, ``2.4 GHz``, ``0.1 m``, ``8 wavelengths``, ``64 MiB``): run logs, settings, geometry."""
    problems, lines = [], prose(text)
    for (n, line), (n_next, follow) in zip(lines, [*lines[1:], (0, "")]):
        for written, value, half, signed, pct in figures(line, follow if n_next == n + 1 else ""):
            held_ = held.holds(value, half, signed) or (pct and held.holds(value / 100, half / 100, signed))
            if not held_ and written.lstrip("+-−").rstrip("%x") not in held.paper:
                problems.append(f"{name}:{n}: {written} ({line.strip()[:100]})")
    return problems


def supplement(root: Path) -> Path | None:
    """The paper's supplement beside the repository at ``root`` (``../shared/seed/...``), None when absent."""
    path = root.resolve().parent / SUPPLEMENT
    return path if path.is_file() else None


def readme_problems(folder: Path, paper: Path | None) -> list[str]:
    """The figures ``folder``'s README.md states that its record (the folder's files) and ``paper`` do not hold."""
    readme = folder / "README.md"
    return not_held(readme.read_text(), record_numbers(folder, paper), str(readme))


def named_records(text: str, sweeps: Path) -> list[Path]:
    """The folders of ``sweeps`` a page names: ``sweeps/NAME`` anywhere in its text (a path, a figure, a link, a
    directive's PATH: include, headline, choose, interp), a study or search directive's NAME, a link to the
    Records page's entry (``records.md#NAME``)."""
    names = {next(g for g in m.groups() if g) for m in NAMED.finditer(text)}
    return sorted(sweeps / n for n in names if (sweeps / n).is_dir())


def pages_problems(root: Path, pages: list[Path] | None = None) -> list[str]:
    """The figures the site's pages (``docs/**/*.md`` but the Reproducibility log, ``docs/reproducibility.md``,
    whose timings and machines are its subject) and the repository's README.md state that neither the records the
    page names (:func:`named_records`: their files, as :func:`record_numbers` reads them) nor the paper's text
    hold.  Every record as every page's record would hold most two-decimal figures by chance.  A page that states
    such figures and names no record is told so."""
    if pages is None:
        pages = [p for p in sorted((root / "docs").rglob("*.md")) if p.name != "reproducibility.md"]
        pages.append(root / "README.md")
    tokens, records, problems = paper_tokens(supplement(root)), {}, []
    for page in pages:
        text, name = page.read_text(), str(page.relative_to(root))
        folders = named_records(text, root / "sweeps")
        records.update({f: record_numbers(f).values for f in folders if f not in records})
        found = not_held(text, Held(sorted(v for f in folders for v in records[f]), tokens), name)
        tell = "" if folders else " [the page names no record: sweeps/NAME, a gen: study/search NAME, records.md#NAME]"
        problems += [p + tell for p in found]
    return problems
