"""A study record's README: the figures generated from its files, and the check that a README or a page states
no figure its record does not hold.

graf-report writes, into the study folder's ``README.md``, a block between :data:`START` and :data:`END`: the
study's tables (:func:`graf.reports.published.study_tables`, split to at most :data:`MAX_COLUMNS` columns) and the
summary of its paired intervals (``intervals.json``).  The text around the block is the record's own and is kept.
:func:`refresh` rewrites the block from the folder's ``report.json``, ``rows.json`` and ``intervals.json`` alone
(``graf-report runs=FOLDER readme_only=true``, ``python scripts/record_readmes.py``).

:func:`not_held` reads the figures a markdown file states and names those its record does not hold
(:func:`readme_problems` for a record's README, :func:`pages_problems` for the site's pages, each page's record the
folders of ``sweeps/`` it names).
"""

from __future__ import annotations

import bisect
import json
import math
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from graf.errors import UserError
from graf.io import atomic_write_text
from graf.metrics.names import REGISTRY
from graf.reports import axes
from graf.reports.published import md, study_tables

START = "<!-- graf-report: generated from report.json, rows.json, intervals.json; do not edit -->"
END = "<!-- /graf-report -->"
MAX_COLUMNS = 7
SIGNED = REGISTRY["psnr"].difference_fmt  # a difference of PSNR (dB); -0.00: below zero by less than the last digit
AXIS_WORDS = {"trained_on": "trained on", "train_band": "train band", "finetune": "fine-tuned",
              "eval_scene": "tested on", "eval_band": "test band"}  # fmt: skip
SUMMARY_ORDER = ("psnr", "ssim", "lpips", "mse")  # the summary's metric order; any other (a plugin's) after them


def _numeric(cell: str) -> bool:
    return cell == "-" or re.match(r"^[-+]?\d", cell) is not None


def split_table(lines: list[str], max_columns: int = MAX_COLUMNS) -> list[str]:
    """A markdown table (its lines) as tables of at most ``max_columns`` columns: the leading label columns (those
    with a cell that is not a figure) repeated in each, the figure columns shared out evenly."""
    rows = [[c.strip() for c in line.strip().strip("|").split(" | ")] for line in lines if not line.startswith("|-")]
    header, body = rows[0], rows[1:]
    keys = next((i for i in range(len(header)) if all(_numeric(r[i]) for r in body)), len(header))
    values = list(range(keys, len(header)))
    if len(header) <= max_columns or not values:
        return ["\n".join(lines)]
    n = math.ceil(len(values) / max(1, max_columns - keys))
    size = math.ceil(len(values) / n)
    out = []
    for k in range(0, len(values), size):
        cols = list(range(keys)) + values[k : k + size]
        out.append(md([header[i] for i in cols], [[r[i] for i in cols] for r in body]))
    return out


def compact(text: str, max_columns: int = MAX_COLUMNS) -> str:
    """``text`` (markdown) with every table wider than ``max_columns`` split by :func:`split_table`."""
    out, table = [], []
    for line in [*text.split("\n"), ""]:
        if line.startswith("|"):
            table.append(line)
            continue
        if table:
            out.append("\n\n".join(split_table(table, max_columns)))
            table = []
        out.append(line)
    return "\n".join(out[:-1])


def _load(path: Path, required: bool = True):
    if not path.is_file():
        if required:
            raise UserError(f"{path}: missing (graf-report writes it; the README's tables are made from it)")
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not valid JSON ({e})") from None


def _diff(c: dict) -> str:
    return SIGNED.format(c["diff"])


def _ends(c: dict) -> str:  # an interval of PSNR differences
    return f"[{SIGNED.format(c['low'])}, {SIGNED.format(c['high'])}]"


def _interval(c: dict | None) -> str:
    return f"{_diff(c)} {_ends(c)} {c['verdict'].split()[0]}" if c else "-"


def verdicts(rows: list[dict]) -> str:
    """Per (method, reference, metric), over the cells: the verdicts, the range of the differences and the widest
    reach of an interval from its difference."""
    groups = defaultdict(list)
    for r in rows:
        for ref in ("knn", "knn-dl"):
            if r.get(f"vs_{ref}"):
                groups[(r["method"], ref, r["metric"])].append(r[f"vs_{ref}"])
    order = {m: i for i, m in enumerate(SUMMARY_ORDER)}
    body = []
    for (method, ref, metric), cs in sorted(groups.items(), key=lambda kv: (*kv[0][:2], order.get(kv[0][2], 9))):
        form = REGISTRY[metric].difference_fmt if metric in REGISTRY else "{:+.3g}"
        counts = defaultdict(int)
        for c in cs:
            counts[c["verdict"].split()[0]] += 1
        diffs = sorted(c["diff"] for c in cs)
        reach = max(max(c["diff"] - c["low"], c["high"] - c["diff"]) for c in cs)
        spread = f"{form.format(diffs[0])} to {form.format(diffs[-1])}"
        told = ", ".join(f"{n} {v}" for v, n in sorted(counts.items()))
        body.append([method, ref.upper(), metric.upper(), told, spread, form.format(reach).lstrip("+")])
    head = ["method", "minus", "metric", "verdicts (cells)", "differences", "widest reach"]
    return md(head, body)


PAIRS = (("trained_on", "eval_scene"), ("train_band", "eval_band"))  # shown as "from -> to"


def _cell_label(rows: list[dict]) -> tuple[str, list[str], list[str]]:
    """(the header of the cell column, each row's cell: the settings that vary over ``rows``, a train / test pair
    as ``a -> b``; the settings with one value, as 'name value')."""
    names = [k for k in axes.AXIS_NAMES if rows and k in rows[0]]
    varying = [k for k in names if len({str(r[k]) for r in rows}) > 1]
    same = [f"{AXIS_WORDS.get(k, k)} {rows[0][k]}" for k in names if k not in varying and rows[0][k] not in ("-", None)]
    pair = next((p for p in PAIRS if set(p) <= set(varying)), None)
    rest = [k for k in varying if not pair or k not in pair]
    head = ([" -> ".join(AXIS_WORDS[k] for k in pair)] if pair else []) + [AXIS_WORDS.get(k, k) for k in rest]
    labels = []
    for r in rows:
        cell = [f"{r[pair[0]]} -> {r[pair[1]]}"] if pair else []
        labels.append(", ".join(cell + [f"L = {r[k]}" if k == "L" else str(r[k]) for k in rest]) or "-")
    return ", ".join(head) or "cell", labels, same


def cells(rows: list[dict]) -> str:
    """PSNR per cell: the mean over the test spectra, the seeds' spread, and each difference to KNN and KNN-DL."""
    rows = [r for r in rows if r["metric"] == "psnr"]
    label, labels, same = _cell_label(rows)
    seeds = any(r["n_seeds"] > 1 for r in rows)
    refs = [ref for ref in ("knn", "knn-dl") if any(r.get(f"vs_{ref}") for r in rows)]
    counts = {(r["n_seeds"], r["n_spectra"]) for r in rows}
    head = [label, "method", "mean (dB)"]
    head += ["seed spread"] * seeds + ["spectra"] * (len(counts) > 1) + [f"minus {ref.upper()}" for ref in refs]
    body = [
        [cell, r["method"], f"{r['mean']:.2f}"]
        + [f"{r['seed_spread']:.2f}"] * seeds
        + [str(r["n_spectra"])] * (len(counts) > 1)
        + [_interval(r.get(f"vs_{ref}")) for ref in refs]
        for r, cell in zip(rows, labels)
    ]
    if len(counts) == 1:
        n_seeds, n_spectra = counts.pop()
        same += [f"{n_seeds} seed{'s' * (n_seeds > 1)}", f"{n_spectra} test spectra"]
    return md(head, body) + (f"\n\nEvery row: {', '.join(same)}." if same else "")


def changes(record: dict) -> list[str]:
    """The PSNR changes with L (from L = 2 and from L = 4) and the band transfers of ``record`` (intervals.json)."""
    out = []
    ls = [c for c in record.get("L_changes") or [] if c["metric"] == "psnr" and c["L_to"] > c["L_from"]]
    ls.sort(key=lambda c: (c["method"], c["L_from"], c["L_to"]))
    if ls:
        word = {"ahead": "rises", "behind": "falls"}
        body = [[c["method"], f"{c['L_from']} -> {c['L_to']}", _diff(c), _ends(c),
                 word.get(c["verdict"], c["verdict"].split()[0])] for c in ls]  # fmt: skip
        out.append(
            "PSNR change with L, pooled over the trained-on / test-scene pairs, paired by spectrum:\n\n"
            + md(["method", "L", "change (dB)", "95% interval", "verdict"], body)
        )
    bands = [c for c in record.get("band_transfers") or [] if c["metric"] == "psnr"]
    if bands:
        body = [[c["method"], c["train_band"], c["eval_band"], _diff(c), _ends(c), c["verdict"].split()[0]]
                for c in bands]  # fmt: skip
        out.append(
            "PSNR of a model trained at another band minus the model trained at the test band, paired by spectrum:\n\n"
            + md(["method", "trained at", "tested at", "difference (dB)", "95% interval", "verdict"], body)
        )
    return out


def intervals_summary(record: dict) -> str:
    """The paired comparisons of ``intervals.json``, compact: the verdicts per metric, PSNR per cell, the changes."""
    parts = [
        "Each trained method minus KNN and minus KNN-DL on the same test spectra: the difference of the means, its "
        f"{record.get('confidence', 0.95):.0%} interval (paired bootstrap over spectra, widened to include every "
        "seed's difference) and verdict (`graf.reports.statistics`); the widest reach is the largest distance from "
        "a difference to an end of its interval.",
        verdicts(record["rows"]),
        cells(record["rows"]),
        *changes(record),
    ]
    return "\n\n".join(parts)


def block(folder: Path) -> str:
    """The generated block of the study record in ``folder``, between :data:`START` and :data:`END`."""
    report = _load(folder / "report.json")
    rows = (_load(folder / "rows.json") or {}).get("rows")
    if not isinstance(rows, list):
        raise UserError(f"{folder / 'rows.json'}: no list 'rows'")
    intervals = _load(folder / "intervals.json", required=False)
    tables = study_tables(report, rows)  # none for a study shape the site has no table of: no empty heading
    parts = ["## Tables", compact("\n\n".join(tables))] if tables else []
    if intervals and intervals.get("rows"):
        parts += ["## Paired intervals", compact(intervals_summary(intervals))]
    sources = "`report.json`, `rows.json`" + (" and `intervals.json`" if intervals else "")
    parts.append(f"*Generated by graf-report from {sources}; every metric of every cell is in the files.*")
    return "\n".join([START, "", "\n\n".join(parts), "", END])


def with_block(text: str, generated: str, title: str, name: str = "README.md") -> str:
    """``text`` (the README ``name``, empty if new) with its generated block replaced by ``generated`` (appended if
    it has none; a new README starts with ``# title``)."""
    if START in text:
        before, rest = text.split(START, 1)
        if END not in rest:
            raise UserError(f"{name}: its generated block has no end marker {END}")
        return before + generated + rest.split(END, 1)[1]
    if not text.strip():
        return f"# {title}\n\n{generated}\n"
    return text.rstrip("\n") + "\n\n" + generated + "\n"


def refresh(folder: Path) -> Path:
    """Rewrite the generated block of ``folder``'s README.md from the folder's own record files (atomically)."""
    folder = Path(folder)
    readme = folder / "README.md"
    text = readme.read_text() if readme.is_file() else ""
    new = with_block(text, block(folder), folder.name, str(readme))
    if new != text:
        atomic_write_text(readme, new)
    return readme


# --- the check: every figure a README or a page states is held by its record -------------------------------------

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
