"""A judged claim's cells, the one shape the paper's paired claims and the platform's findings share: each cell a
``method - reference`` difference with its 95% interval and the interval's verdict, and the ledger's two columns
(``platform``: the differences, ``interval``: the intervals) written from them."""

from __future__ import annotations


def cell(name: str, c: dict) -> dict:
    """The cell ``name`` of a record's comparison ``c`` (``diff``, ``low``, ``high``, ``verdict``, and where the
    record has it, ``share_ahead``)."""
    out = {"cell": name, "diff": c["diff"], "low": c["low"], "high": c["high"], "verdict": c["verdict"]}
    return out if c.get("share_ahead") is None else {**out, "share_ahead": c["share_ahead"]}


def columns(cells: list[dict]) -> dict:
    """The ledger's platform and interval columns of ``cells``."""
    return {
        "platform": "; ".join(f"{c['cell']}: {c['diff']:+.2f}" for c in cells),
        "interval": "; ".join(f"{c['cell']}: [{c['low']:+.2f}, {c['high']:+.2f}]" for c in cells),
    }
