"""How each claim is judged from its record (``kind``: paired, value, difference, change, transfer, note) and the
ledger's rows and files (the rules: :mod:`graf.reports.claims`)."""

from __future__ import annotations

import csv
import io
import logging
from pathlib import Path

from omegaconf import DictConfig

from graf.app.config import task_wrapper
from graf.errors import ConfigError
from graf.io import atomic_write_bytes, atomic_write_json
from graf.reports.claims.cells import cell, columns
from graf.reports.claims.claims_file import check_claim, check_claims, check_records, read_claims
from graf.reports.claims.findings import NO_RECORD, distance_cells, is_finding, judge_distance
from graf.reports.claims.findings import VERDICTS as FINDING_VERDICTS
from graf.reports.claims.ledger import VERDICTS, value_interval, write_page
from graf.reports.claims.records import density_reason, load_record, lookup, untrusted_timings
from graf.reports.rows import short_scenes
from graf.reports.statistics import HIGHER_IS_BETTER

log = logging.getLogger("graf")

COLUMNS = ("id", "source", "claim", "paper", "platform", "interval", "verdict", "reason", "record", "command")


def _match(row: dict, cell: dict | list) -> bool:
    """A row of the record is in the claim's ``cell``: every key's value (one, or any of a list); a list of such
    dicts is any of them (pairs: ``[{trained_on: a, eval_scene: [b, c]}, ...]``)."""
    if isinstance(cell, list):
        return any(_match(row, c) for c in cell)
    for k, want in cell.items():
        have = row.get(k)
        if isinstance(want, list):
            if str(have) not in {str(w) for w in want}:
                return False
        elif str(have) != str(want):
            return False
    return True


def _pair(r: dict) -> str:
    """A study row's cell as the ledger names it: ``trained on -> tested on`` (or the test scene alone)."""
    return f"{short_scenes(r['trained_on'])} -> {r['eval_scene']}" if r.get("trained_on") else r["eval_scene"]


def paired_cells(claim: dict, data: dict) -> list[dict]:
    """The cells of a paired claim: per selected row, ``method`` minus ``reference`` (``cell``, ``diff``, ``low``,
    ``high``, the interval's ``verdict``)."""
    rows = [
        r for r in data.get("rows", []) if r.get("method") == claim["method"] and r.get("metric") == claim["metric"]
    ]
    rows = [r for r in rows if _match(r, claim.get("cell") or {})]
    return [cell(_pair(r), r[f"vs_{claim['reference']}"]) for r in rows if r.get(f"vs_{claim['reference']}")]


def judge_paired(claim: dict, data: dict) -> dict:
    cells = paired_cells(claim, data)
    if not cells:
        return {"verdict": "not reproduced", "reason": "no such comparison in the record"}
    if claim.get("margin") is not None or claim.get("share") is not None:
        return _judge_target(claim, cells)
    verdict, reason = _direction([c["verdict"] for c in cells], "ahead")
    return {**columns(cells), "verdict": verdict, "reason": reason}


def _percent(x: float) -> str:
    return f"{100 * x:.0f}%"


def _signed(x: float) -> str:
    return f"{x:+.2f}"


def _judge_target(claim: dict, cells: list[dict]) -> dict:
    """A paired target: every cell ahead by at least ``margin`` (in the metric's better direction, its interval
    excluding 0), or better on at least ``share`` of its spectra."""
    if claim.get("share") is not None and claim.get("margin") is not None:
        raise ConfigError(f"claim {claim.get('id')!r}: give margin or share, not both (one target a row)")
    if claim.get("share") is not None:
        if any("share_ahead" not in c for c in cells):
            return {"verdict": "not reproduced", "reason": "the record holds no share of spectra (graf-report again)"}
        want, got = float(claim["share"]), {c["cell"]: c["share_ahead"] for c in cells}
        fmt = _percent
        out = {"platform": "; ".join(f"{k}: {fmt(v)}" for k, v in got.items())}
        ok = {k: v >= want for k, v in got.items()}
    else:
        want = float(claim["margin"])
        up = HIGHER_IS_BETTER[str(claim["metric"])]
        got = {c["cell"]: (c["diff"] if up else -c["diff"]) for c in cells}
        fmt = _signed
        out = columns(cells)
        ok = {c["cell"]: got[c["cell"]] >= want and c["verdict"] == "ahead" for c in cells}
    if all(ok.values()):
        return {**out, "verdict": "holds", "reason": f"every cell reaches the target's {fmt(want)}"}
    worst = min(got, key=got.get)
    short = f"{100 * (want - got[worst]):.0f} points" if claim.get("share") is not None else f"{want - got[worst]:.2f}"
    reason = (
        f"{sum(ok.values())} of {len(ok)} cells reach the target's {fmt(want)}; furthest short: {worst}, "
        f"{fmt(got[worst])} (missed by {short})"
    )
    return {**out, "verdict": "not reproduced", "reason": reason}


def _direction(verdicts: list[str], want: str) -> tuple[str, str]:
    """The ledger's verdict and reason from the cells' verdicts, the paper saying each is ``want`` (ahead/behind)."""
    other = "behind" if want == "ahead" else "ahead"
    n = len(verdicts)
    if all(v == want for v in verdicts):
        return "holds", f"{want} in {'its one cell' if n == 1 else f'all {n} cells'} (interval excludes 0)"
    if any(v == other for v in verdicts):
        return "refuted", f"{other} in {sum(v == other for v in verdicts)} of {n} cells"
    n_level, n_want = sum(v.startswith("level") for v in verdicts), sum(v == want for v in verdicts)
    also = f"{want} in {n_want}, " if n_want else ""
    return "not reproduced", f"{also}interval includes 0 in {n_level} of {n} cells"


def transfer_cells(claim: dict, data: dict) -> list[dict]:
    """The cells of a transfer claim: per band pair of the record, ``train band -> test band``."""
    want = {"method": claim["method"], "metric": claim["metric"], **(claim.get("cell") or {})}
    found = [c for c in data.get("band_transfers", []) if _match(c, want)]
    return [cell(f"{c['train_band']} -> {c['eval_band']}", c) for c in found]


def judge_transfer(claim: dict, data: dict) -> dict:
    expect = str(claim.get("expect", "behind"))
    if expect not in ("ahead", "behind"):
        raise ConfigError(f"claim {claim.get('id')!r}: expect must be 'ahead' or 'behind', got {expect!r}")
    cells = transfer_cells(claim, data)
    if not cells:
        return {"verdict": "not reproduced", "reason": "no band transfer in the record"}
    verdict, reason = _direction([c["verdict"] for c in cells], expect)
    return {**columns(cells), "verdict": verdict, "reason": reason}


def change_cells(claim: dict, data: dict) -> list[dict]:
    """The one cell of a change claim: the record's first L change of ``method`` and ``metric`` from ``L_from`` to
    ``L_to``, or none."""
    want = {k: claim[k] for k in ("method", "L_from", "L_to", "metric")}
    found = [c for c in data.get("L_changes", []) if all(str(c.get(k)) == str(v) for k, v in want.items())]
    return [cell(f"L = {claim['L_from']} -> {claim['L_to']}", c) for c in found[:1]]


def judge_change(claim: dict, data: dict) -> dict:
    cells = change_cells(claim, data)
    if not cells:
        want = {k: claim[k] for k in ("method", "L_from", "L_to", "metric")}
        return {"verdict": "not reproduced", "reason": f"no L change {want} in the record"}
    c = cells[0]
    out = {"platform": f"{c['diff']:+.2f}", "interval": f"[{c['low']:+.2f}, {c['high']:+.2f}]"}
    if claim.get("tolerance") is not None:
        tol = float(claim["tolerance"])
        inside = -tol <= c["low"] and c["high"] <= tol
        out.update(
            verdict="holds" if inside else "not reproduced",
            reason=f"the interval {'lies' if inside else 'does not lie'} within +-{tol:g}",
        )
        return out
    sign = 1.0 if float(claim["paper_value"]) >= 0 else -1.0
    if sign * c["low"] > 0 or sign * c["high"] < 0:
        same = sign * c["diff"] > 0
        out.update(
            verdict="holds" if same else "refuted",
            reason=f"the interval excludes 0 ({'the paper' if same else 'against the paper'}'s direction)",
        )
    else:
        out.update(verdict="not reproduced", reason="the interval includes 0")
    return out


def _reaches(value: float, paper: float, higher: bool) -> bool:
    return value >= paper if higher else value <= paper


def judge_value(claim: dict, data: dict) -> dict:
    """One figure of a record against the paper's (``paper_value``): ``key``, less ``minus`` or divided by ``over``
    (a difference or a ratio of two figures of the record) when given; ``against`` names whose figure it is (the
    paper's by default; a platform target's, an issue's, where the row is one)."""
    try:
        value = float(lookup(data, claim["key"]))
        if claim.get("minus"):
            value -= float(lookup(data, claim["minus"]))
        if claim.get("over"):
            value /= float(lookup(data, claim["over"]))
    except (KeyError, IndexError, TypeError, ValueError, ZeroDivisionError) as exc:
        return {"verdict": "not reproduced", "reason": f"the record has no {claim['key']} ({exc})"}
    paper, higher = float(claim["paper_value"]), bool(claim.get("higher_is_better", True))
    fmt, whose = claim.get("format", ".2f"), claim.get("against", "the paper's")
    out = {"platform": format(value, fmt)}
    if _reaches(value, paper, higher):
        out.update(verdict="holds", reason=f"{format(value, fmt)} reaches {whose} {format(paper, fmt)}")
    else:
        short = abs(paper - value)
        out.update(
            verdict="not reproduced",
            reason=f"{format(value, fmt)} against {whose} {format(paper, fmt)} (missed by {format(short, fmt)})",
        )
    return out


JUDGES = {
    "paired": judge_paired,
    "value": judge_value,
    "difference": judge_value,
    "change": judge_change,
    "transfer": judge_transfer,
    "distance": judge_distance,  # a finding beyond the paper (graf.reports.claims.findings)
}


def judge(claim: dict, root: Path) -> dict:
    """One ledger row of ``claim`` from the records under ``root``."""
    row = {c: "" for c in COLUMNS}
    row.update({k: str(claim.get(k, "")) for k in ("id", "source", "claim", "paper", "record", "command")})
    check_claim(claim)
    kind = claim["kind"]
    if kind == "note":
        row.update(platform=str(claim.get("platform", "")), verdict="not comparable", reason=str(claim["reason"]))
        data = load_record(root, claim["record"]) if claim.get("key") else None
        if untrusted := untrusted_timings(claim, data or {}):
            row["reason"] += (
                f"; a timing it quotes is not trusted, its record marks it disturbed ({'; '.join(untrusted)})"
            )
        return row
    data = load_record(root, claim["record"])
    if data is None:
        row.update(
            verdict=NO_RECORD if is_finding(claim) else "not reproduced", reason=f"no record yet: {claim['record']}"
        )
        return row
    if claim.get("paper_density"):
        why = density_reason(data)
        if why:
            judged = value_interval(claim, root) or JUDGES[kind](claim, data)
            row.update(platform=judged.get("platform", ""), interval=judged.get("interval", ""))
            row.update(verdict="not comparable", reason=why)
            return row
    judged = value_interval(claim, root) or JUDGES[kind](claim, data)
    row.update({k: v for k, v in judged.items() if k in COLUMNS})
    if claim.get("reason"):
        row["reason"] = f"{row['reason']}; {claim['reason']}" if row["reason"] else str(claim["reason"])
    if untrusted := untrusted_timings(claim, data):
        row["reason"] += f"; a timing it reads is not trusted, its record marks it disturbed ({'; '.join(untrusted)})"
    return row


def ledger(claims: list[dict], root: Path, where: str = "claims") -> list[dict]:
    """The ledger's rows of ``claims`` (read from ``where``: named in a refusal) from the records under ``root``."""
    check_claims(claims, where)
    return [judge(c, root) for c in claims]


CELLS = {"paired": paired_cells, "change": change_cells, "transfer": transfer_cells, "distance": distance_cells}


def claim_cells(claim: dict, root: Path) -> list[dict]:
    """The cells with an interval that ``claim`` reads from its record under ``root`` (its figure's rows); none
    for a claim of another kind or without a record."""
    if claim.get("kind") == "value" and claim.get("seeds"):
        judged = value_interval(claim, root)
        return [judged["cell"]] if "cell" in judged else []
    if claim.get("kind") not in CELLS:
        return []
    data = load_record(root, claim["record"])
    return [] if data is None else CELLS[claim["kind"]](claim, data)


def write_ledger(claims: list[dict], rows: list[dict], root: Path, out: Path) -> None:
    """The ledger of ``claims`` (``rows``, from the records under ``root``) in ``out``: ``claims.csv`` (the machine
    form), ``results.json``, and the page to read, ``claims.md`` with a forest plot per claim with intervals
    (:func:`graf.reports.ledger.write_page`)."""
    out.mkdir(parents=True, exist_ok=True)
    text = io.StringIO()
    w = csv.DictWriter(text, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    atomic_write_bytes(out / "claims.csv", text.getvalue().encode())
    write_page(claims, rows, {c["id"]: claim_cells(c, root) for c in claims}, root, out)
    atomic_write_json(out / "results.json", {"task": "claims", **counts(claims, rows), "rows": rows})


def counts(claims: list[dict], rows: list[dict]) -> dict:
    """``{"counts": the paper's claims (and their re-runs) per verdict, "findings": the findings per verdict}``."""
    finding = {c["id"]: is_finding(c) for c in claims}
    return {
        "counts": {v: sum(r["verdict"] == v for r in rows if not finding[r["id"]]) for v in VERDICTS},
        "findings": {v: sum(r["verdict"] == v for r in rows if finding[r["id"]]) for v in FINDING_VERDICTS},
    }


@task_wrapper
def claims(cfg: DictConfig) -> dict:
    """graf-claims: the ledger of ``cfg.claims`` from the records under ``cfg.records``, written into ``cfg.out``."""
    cfg, claims, where = read_claims(cfg)
    root = Path(str(cfg.records))
    check_records(root)
    rows = ledger(claims, root, where)
    out = Path(str(cfg.out))
    write_ledger(claims, rows, root, out)
    for r in rows:
        log.info("%-28s %-15s %s", r["id"], r["verdict"], r["platform"])
    log.info("ledger: %s (the page: %s)", out / "claims.csv", out / "claims.md")
    return counts(claims, rows)
