"""A study record's README: the figures generated from its files.

graf-report writes, into the study folder's ``README.md``, a block between :data:`START` and :data:`END`: the
study's tables (:func:`graf.reports.published.study_tables`, split to at most :data:`MAX_COLUMNS` columns) and the
summary of its paired intervals (``intervals.json``).  The text around the block is the record's own and is kept.
:func:`refresh` rewrites the block from the folder's ``report.json``, ``rows.json`` and ``intervals.json`` alone
(``graf-report runs=FOLDER readme_only=true``, ``python scripts/record_readmes.py``).

The check that a README or a page states no figure its record does not hold is the site's
(``docs_hooks/stated_figures.py``).
"""

from __future__ import annotations

import json
import math
import re
from collections import defaultdict
from pathlib import Path

from graf.errors import UserError
from graf.io import atomic_write_text
from graf.metrics.names import REGISTRY
from graf.reports import axes
from graf.reports.distance import markdown as distance_markdown
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
    distance = _load(folder / "distance.json", required=False)
    if distance:
        parts += ["## Neighbour distance", compact(distance_markdown(distance))]
    sources = "`report.json`, `rows.json`" + (", `intervals.json`" if intervals and distance else "")
    sources += " and `distance.json`" if distance else (" and `intervals.json`" if intervals else "")
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
