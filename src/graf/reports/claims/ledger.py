"""The claims ledger as a page to read: ``claims.md`` (``docs/claims.md`` includes it) and a forest plot
``<id>.png`` per claim with intervals, beside the machine form ``claims.csv`` (:mod:`graf.reports.claims.judge`).

The page opens with the counts per verdict, one line each, every claim named and linked to its section; the
claims judged against another figure than the paper's (an issue's target: the claim's ``against``) are counted
apart.  Then one section per claim, headed by its ``title``: its source and what the paper says, the platform's
figure (for a comparison: a table of its cells with their 95% intervals and the forest plot, drawn from the same
interval records the verdict reads), the verdict and its reason, the record and the command.
"""

from __future__ import annotations

import json
import re
import textwrap
from pathlib import Path

import matplotlib.pyplot as plt  # on the Agg backend: graf.plotting (below) sets it
import numpy as np

from graf.io import atomic_write_bytes
from graf.metrics.names import REGISTRY
from graf.plotting import save_figure
from graf.reports.claims.findings import VERDICTS as FINDING_VERDICTS
from graf.reports.claims.findings import is_finding
from graf.reports.statistics import HIGHER_IS_BETTER, paired_difference
from graf.run.per_spectrum import PER_SPECTRUM_FILE, read_per_spectrum

VERDICTS = ("holds", "refuted", "not reproduced", "not comparable")
WIDTH = 88  # a command's lines in its code block, continued with " \"
TITLE_CHARS = 60  # a forest plot's title lines (centred over the axes, right of the cell labels): wrapped, never cut
TOKEN = re.compile(r"(?:'[^']*'|\"[^\"]*\"|\S)+")  # a word of a command, quotes kept whole


def write_page(claims: list[dict], rows: list[dict], cells: dict[str, list[dict]], root: Path, out: Path) -> Path:
    """``out/claims.md`` of the ledger ``rows`` of ``claims``, and ``out/<id>.png`` for each claim with ``cells``
    (:func:`graf.reports.claims.judge.claim_cells`); a figure of a claim no longer in the ledger is removed."""
    figures = set()
    for claim in claims:
        if cells.get(claim["id"]):
            forest_plot(claim, cells[claim["id"]], out / f"{claim['id']}.png")
            figures.add(f"{claim['id']}.png")
    for stale in out.glob("*.png"):
        if stale.name not in figures:
            stale.unlink()
    text = page(claims, rows, cells, root, out)
    return atomic_write_bytes(out / "claims.md", text.encode())


def page(claims: list[dict], rows: list[dict], cells: dict[str, list[dict]], root: Path, out: Path) -> str:
    """The ledger's page: the summary, then a section per claim of the paper (in the config's order), a re-run of
    it (``of``: the same claim on another record, at other budgets) a part of that section with its own verdict;
    then the findings beyond the paper, counted apart (:mod:`graf.reports.claims.findings`)."""
    by_id = {c["id"]: c for c in claims}
    parts = [summary(claims, rows)]
    figures = {r["id"]: _link(out / f"{r['id']}.png", root) for r in rows if cells.get(r["id"])}
    for row in rows:
        if by_id[row["id"]].get("of") or is_finding(by_id[row["id"]]):
            continue
        for r in [row, *(r for r in rows if by_id[r["id"]].get("of") == row["id"])]:
            parts.append(section(by_id[r["id"]], r, cells.get(r["id"]) or [], figures.get(r["id"]), root))
    parts.append(findings_part(claims, rows, cells, root, figures))  # the findings beyond the paper, counted apart
    return "\n\n".join(p for p in parts if p) + "\n"


def _link(path: Path, root: Path) -> str:
    """``path`` as the page names it: from the repository root (``sweeps/claims/x.png``, as a docs page links a
    published figure) when it lies under ``root``."""
    try:
        return path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return path.as_posix()


def title(claim: dict) -> str:
    return str(claim.get("title") or claim["id"])


def summary(claims: list[dict], rows: list[dict]) -> str:
    """The claims counted per verdict, one line each naming its claims (linked to their sections), a claim's
    re-runs (``of``) named beside it with their own verdicts, not counted again; the paper's claims first, then
    each group judged against another figure (``against``)."""
    by_id = {c["id"]: c for c in claims}
    groups: dict[str | None, list[dict]] = {}
    for row in rows:
        if not by_id[row["id"]].get("of") and not is_finding(by_id[row["id"]]):
            groups.setdefault(by_id[row["id"]].get("against"), []).append(row)
    out = []
    for against, group in sorted(groups.items(), key=lambda g: g[0] is not None):
        whose = "The paper's claims" if against is None else f"Judged against {against} figure, not the paper's"
        lines = [f"**{whose}** ({len(group)}):", ""]
        for verdict in VERDICTS:
            named = [_named(r, rows, by_id) for r in group if r["verdict"] == verdict]
            lines.append(f"- **{verdict}** ({len(named)}): {', '.join(named) or 'none'}")
        out.append("\n".join(lines))
    return "\n\n".join(out)


def _named(row: dict, rows: list[dict], by_id: dict) -> str:
    """A claim linked to its section, with its re-runs' verdicts: ``[title](#id) (at the earlier budgets: ...)``."""
    reruns = [r for r in rows if by_id[r["id"]].get("of") == row["id"]]
    variants = [_variant(by_id[r["id"]]) for r in reruns]
    also = "; ".join(f"[{v[:1].lower() + v[1:]}](#{r['id']}): {r['verdict']}" for v, r in zip(variants, reruns))
    return f"[{title(by_id[row['id']])}](#{row['id']})" + (f" ({also})" if also else "")


def _variant(claim: dict) -> str:
    return str(claim.get("variant") or title(claim))


def _stop(text: str) -> str:
    """``text`` ending with a full stop."""
    text = str(text).strip()
    return text if not text or text.endswith((".", "?", "!")) else text + "."


def _sentence(text: str) -> str:
    """``text`` as a sentence: its first letter capital, a full stop at the end."""
    text = _stop(text)
    return text[:1].upper() + text[1:]


def section(claim: dict, row: dict, cells: list[dict], figure: str | None, root: Path) -> str:
    """One claim's section: heading, source and statement, the platform's figure, verdict, record, command."""
    speaker = _sentence(claim.get("against", "the paper's").removesuffix("'s")).rstrip(".")  # The paper
    said = f"*Source: {_stop(row['source'])}* {speaker}: {_sentence(row['claim'])} Its figure: {_stop(row['paper'])}"
    parts = [
        f"### {_variant(claim)} {{#{row['id']}}}" if claim.get("of") else f"## {title(claim)} {{#{row['id']}}}",
        "" if claim.get("of") else said,
        platform(claim, row, cells, figure),
        f"Verdict: **{row['verdict']}**. {_sentence(row['reason'])}",
        record(row["record"], root),
    ]
    if row["command"]:
        lines, jobs = shell_lines(row["command"])
        parts.append("Command:\n\n```bash\n" + "\n".join(wrap(line) for line in lines) + "\n```")
        if jobs:
            parts.append(f"Each job it runs (a value in `<...>` is one of its variants): `{jobs}`")
    return "\n\n".join(p for p in parts if p)


def shell_lines(command: str) -> tuple[list[str], str | None]:
    """A claims file's ``command`` as the exact shell lines to paste (its ``;``-separated commands, one a line) and
    the form of each job it runs (the parenthesised part, where it has one: placeholders such as ``<scene>``, not
    shell), so that the block a reader copies runs as it is."""
    head, jobs, tail = command, None, ""
    if (start := command.find(" (")) >= 0:
        depth = 0
        for i in range(start + 1, len(command)):
            depth += {"(": 1, ")": -1}.get(command[i], 0)
            if depth == 0:
                head, jobs, tail = command[:start], command[start + 2 : i], command[i + 1 :]
                break
    lines = [c.strip() for c in f"{head}{tail}".split(";") if c.strip()]
    return lines, jobs


def _metric(claim: dict) -> tuple[str, str]:
    """The label and unit of the claim's metric (the metric registry's; the name alone for one it lacks)."""
    name = claim.get("metric") or str(claim.get("key", "")).rsplit("/", 1)[-1]  # a value claim's key: test/psnr
    m = REGISTRY.get(str(name))
    return (m.label, m.unit) if m else (str(name), "")


def difference(claim: dict) -> str:
    """What a cell's figure is: ``PSNR, graf-ray-weights minus knn-dl``."""
    label = _metric(claim)[0]
    if claim["kind"] == "change":
        return f"{label} of {claim['method']}, L = {claim['L_to']} minus L = {claim['L_from']}"
    if claim["kind"] == "transfer":
        return f"{label} of {claim['method']}, trained at another band minus at the test band"
    if claim["kind"] == "value":
        return f"test {label}, the mean over the runs' test spectra"
    return f"{label}, {claim['method']} minus {claim['reference']}"


def platform(claim: dict, row: dict, cells: list[dict], figure: str | None) -> str:
    """The platform's figure: the cells' table and forest plot, else the figure beside the paper's, else the
    platform column as prose."""
    if cells:
        unit = _metric(claim)[1]
        head = f"The platform: {difference(claim)}{f' ({unit})' if unit else ''}, per cell, with its 95% interval:"
        body = [[c["cell"], f"{c['diff']:+.2f}", f"[{c['low']:+.2f}, {c['high']:+.2f}]"] for c in cells]
        header = ["cell", f"difference{f' ({unit})' if unit else ''}", "95% interval"]
        if claim.get("share") is not None and all("share_ahead" in c for c in cells):  # a target on that share
            header.append("better on (share of spectra)")
            body = [[*b, f"{100 * c['share_ahead']:.0f}%"] for b, c in zip(body, cells)]
        table = _table(header, body)
        alt = f"{title(claim)}: each cell's difference and 95% interval"
        return f"{head}\n\n{table}\n\n![{alt}]({figure})" if figure else f"{head}\n\n{table}"
    if row["platform"] and claim.get("kind") in ("value", "difference") and claim.get("paper_value") is not None:
        paper = format(float(claim["paper_value"]), claim.get("format", ".2f"))
        whose = claim.get("against", "the paper's")
        return _table(["the platform's figure", f"{whose} figure"], [[row["platform"], paper]])
    if row["platform"]:
        return f"The platform: {_sentence(row['platform'])}"
    return "The platform has no figure for it."


def _table(header: list[str], body: list[list[str]]) -> str:
    esc = lambda s: str(s).replace("|", "\\|").replace("\n", " ")  # noqa: E731
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(esc(c) for c in r) + " |" for r in body])


def record(path: str, root: Path) -> str:
    """Where the figure comes from: the record (as a path: the site publishes the records' figures alone) and its
    folder's README where it has one."""
    if not path:
        return ""
    readme = Path(path).parent / "README.md"
    how = f"; how it was made: `{readme.as_posix()}`" if (root / readme).is_file() else ""
    return f"Record: `{path}`{how}."


def wrap(command: str, width: int = WIDTH) -> str:
    """``command`` in lines of at most ``width`` characters (a longer word alone), broken between words and
    continued with `` \\``, so that the block reads without scrolling and copies as one command."""
    lines, line = [], ""
    for word in TOKEN.findall(command):
        if line and len(line) + 1 + len(word) + 2 > width:
            lines.append(line + " \\")
            line = "    " + word
        else:
            line = f"{line} {word}" if line else word
    return "\n".join(lines + [line])


def forest_plot(claim: dict, cells: list[dict], path: Path) -> Path:
    """Each cell's difference and 95% interval on one axis (the first cell on top), the 0 line, the paper's
    figure as a marker where the claim has one (``paper_value``), and the band a plateau claim allows
    (``tolerance``)."""
    n = len(cells)
    y = np.arange(n)[::-1]
    diff = np.array([c["diff"] for c in cells])
    err = np.array([[c["diff"] - c["low"] for c in cells], [c["high"] - c["diff"] for c in cells]])
    fig, ax = plt.subplots(figsize=(7.0, 1.9 + 0.3 * n), constrained_layout=True)
    if claim.get("tolerance") is not None:
        tol = float(claim["tolerance"])
        ax.axvspan(-tol, tol, color="0.88", label=f"within ±{tol:g} (the paper's plateau)")
    if claim["kind"] != "value":  # a value is no difference: no 0 line
        ax.axvline(0.0, color="0.3", lw=1.0, ls="--", label="0 (no difference)")
    ax.errorbar(diff, y, xerr=err, fmt="o", color="C0", capsize=3, label="the platform: 95% interval")
    whose = claim.get("against") or "the paper's"  # a target of the platform's own: "the target's"
    if claim.get("paper_value") is not None:
        paper = float(claim["paper_value"])
        said = f"{paper:.2f}" if claim["kind"] == "value" else f"{paper:+.2f}"
        ax.plot([paper] * n, y, "D", color="C3", label=f"{whose} figure, {said}")
    if claim.get("margin") is not None:  # the target: ahead by at least this much in every cell
        ax.axvline(float(claim["margin"]), color="C3", lw=1.2, ls=":", label=f"{whose} margin, {claim['margin']:+g}")
    unit = _metric(claim)[1]
    ax.set_xlabel(f"{difference(claim)}{f' ({unit})' if unit else ''}", fontsize=9)
    ax.set_yticks(y, [c["cell"] for c in cells], fontsize=8)
    ax.set_ylim(-0.7, n - 0.3)
    ax.set_title("\n".join(textwrap.wrap(title(claim), TITLE_CHARS)), fontsize=10)  # wrapped, never cut
    fig.legend(fontsize=7, loc="outside lower center", ncols=3, frameon=False)  # below: it hides no interval
    return save_figure(fig, path, dpi=100)


def value_interval(claim: dict, root: Path) -> dict | None:
    """A ``value`` claim with ``seeds`` (its record's runs: results.json paths, the record first): the figure as the
    mean over the runs' test spectra (each spectrum's value averaged over the runs) minus the paper's, with its 95%
    interval (:func:`graf.reports.statistics.paired_difference` against the paper's figure on every spectrum:
    bootstrap over spectra, widened to every run's own difference).  None: the claim has no ``seeds``."""
    if not claim.get("seeds"):
        return None
    metric = str(claim["key"]).rsplit("/", 1)[-1]
    runs = []
    for rel in claim["seeds"]:
        table = root / Path(rel).parent / PER_SPECTRUM_FILE
        if not (root / rel).is_file() or not table.is_file():
            return {"verdict": "not reproduced", "reason": f"no record yet: {rel} with its {PER_SPECTRUM_FILE}"}
        method = json.loads((root / rel).read_text())["method"]
        runs.append({r["id"]: r[metric] for r in read_per_spectrum(table) if r["method"] == method})
    paper = float(claim["paper_value"])
    c = paired_difference(runs, [dict.fromkeys(runs[0], paper)], metric)
    fmt = claim.get("format", ".2f")
    value, low, high = c["diff"] + paper, c["low"] + paper, c["high"] + paper
    told = f"{format(value, fmt)} [{format(low, fmt)}, {format(high, fmt)}], {len(runs)} run{'s' * (len(runs) > 1)}"
    clears = low > paper if HIGHER_IS_BETTER[metric] else high < paper
    return {
        "cell": {
            "cell": f"{len(runs)} run{'s' * (len(runs) > 1)}",
            "diff": value,
            "low": low,
            "high": high,
            "verdict": "holds" if clears else "not reproduced",
        },  # fmt: skip
        "platform": format(value, fmt),
        "interval": f"[{format(low, fmt)}, {format(high, fmt)}]",
        "verdict": "holds" if clears else "not reproduced",
        "reason": f"{told} over {c['n_spectra']} test spectra: the interval "
        + (
            f"clears the paper's {format(paper, fmt)}" if clears else f"does not clear the paper's {format(paper, fmt)}"
        ),
    }


def findings_summary(claims: list[dict], rows: list[dict]) -> str:
    """The findings counted per verdict, one line each naming its findings (linked to their sections)."""
    by_id = {c["id"]: c for c in claims}
    found = [r for r in rows if is_finding(by_id[r["id"]])]
    lines = [f"**Findings beyond the paper** ({len(found)}):", ""]
    for verdict in FINDING_VERDICTS:
        named = [f"[{title(by_id[r['id']])}](#{r['id']})" for r in found if r["verdict"] == verdict]
        lines.append(f"- **{verdict}** ({len(named)}): {', '.join(named) or 'none'}")
    return "\n".join(lines)


def finding_section(claim: dict, row: dict, cells: list[dict], figure: str | None, root: Path) -> str:
    """One finding's section: heading, what it asks, the platform's cells and forest plot, verdict, record,
    command."""
    parts = [
        f"### {title(claim)} {{#{row['id']}}}",
        f"*Not a claim of the paper.* {row['claim']}",
        platform(claim, row, cells, figure),
        f"Verdict: **{row['verdict']}**. {_sentence(row['reason'])}",
        record(row["record"], root) if (root / row["record"]).is_file() else "",  # not run yet: the reason names it
    ]
    if row["command"]:
        lines, _ = shell_lines(row["command"])
        parts.append("Command:\n\n```bash\n" + "\n".join(wrap(line) for line in lines) + "\n```")
    return "\n\n".join(p for p in parts if p)


def findings_part(claims: list[dict], rows: list[dict], cells: dict[str, list[dict]], root: Path, figures: dict) -> str:
    """The ledger page's findings part (empty without findings): its heading, summary and one section each."""
    by_id = {c["id"]: c for c in claims}
    found = [r for r in rows if is_finding(by_id[r["id"]])]
    if not found:
        return ""
    head = (
        "## Findings beyond the paper {#findings}\n\n"
        "Results of the platform's own studies that no claim of the paper states, judged from their records with "
        "the same paired 95% intervals: where a method leads (interval above 0), trails (below) or is level."
    )
    sections = [finding_section(by_id[r["id"]], r, cells.get(r["id"]) or [], figures.get(r["id"]), root) for r in found]
    return "\n\n".join([head, findings_summary(claims, rows), *sections])
