"""The ledger's findings beyond the paper: results of the platform's own studies that no claim of the paper states,
judged from their records with the same intervals, in a section of their own and counted apart from the claims.

One kind so far, ``distance``: a neighbour-distance study's record (``distance.json``,
:mod:`graf.reports.distance`), ``method`` (``graf``: GRaF in the mode of each distance, or a method of the record)
minus ``reference`` (``knn`` or ``knn-dl``) at every (family, distance) of the record, each with its paired 95%
interval.  The finding's verdict says where the method stands (:data:`VERDICTS`): ``leads`` (ahead somewhere,
behind nowhere), ``trails`` (behind somewhere, ahead nowhere), ``level`` (neither anywhere), ``mixed`` (both), or
``not run yet`` (no record); the reason lists the distances of each.  The ledger's page shows them after the
paper's claims, in a part of their own (:func:`graf.reports.claims.ledger.findings_part`).
"""

from __future__ import annotations

from graf.reports.claims.cells import cell, columns

KINDS = ("distance",)
VERDICTS = ("leads", "trails", "level", "mixed", "not run yet")
NO_RECORD = "not run yet"


def is_finding(claim: dict) -> bool:
    return claim.get("kind") in KINDS


def distance_cells(claim: dict, data: dict) -> list[dict]:
    """The cells of a distance finding: per family (training scene) and distance, ``method`` minus ``reference``."""
    out = []
    for family, points in sorted((data.get("differences") or {}).items()):
        for distance in sorted(points, key=float):
            c = (points[distance].get(claim["method"]) or {}).get(f"vs_{claim['reference']}")
            if c is not None:
                out.append(cell(f"{family}, {float(distance):g} λ", c))
    return out


def _where(cells: list[dict], verdict: str) -> str:
    """The cells of one interval verdict, per family: ``conference_v1 at 1, 4 λ``."""
    per: dict[str, list[str]] = {}
    for c in cells:
        if c["verdict"] == verdict or (verdict == "level" and c["verdict"] not in ("ahead", "behind")):
            family, distance = c["cell"].rsplit(", ", 1)
            per.setdefault(family, []).append(distance.removesuffix(" λ"))
    return "; ".join(f"{family} at {', '.join(ds)} λ" for family, ds in per.items())


def judge_distance(claim: dict, data: dict) -> dict:
    """The finding's row: the cells as the platform and interval columns, its verdict, and where it leads, trails
    and is level."""
    cells = distance_cells(claim, data)
    if not cells:
        return {"verdict": NO_RECORD, "reason": f"the record has no {claim['method']} - {claim['reference']} yet"}
    ahead, behind = (any(c["verdict"] == v for c in cells) for v in ("ahead", "behind"))
    verdict = {(True, False): "leads", (False, True): "trails", (False, False): "level"}.get((ahead, behind), "mixed")
    where = {"ahead": "above", "behind": "below", "level": "around"}  # the 95% interval against 0
    said = [(w, _where(cells, w)) for w in where]
    return {
        **columns(cells),
        "verdict": verdict,
        "reason": ". ".join(f"{w.capitalize()} (95% interval {where[w]} 0): {s}" for w, s in said if s),
    }
