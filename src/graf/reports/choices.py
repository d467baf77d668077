"""The choices read off the learning curves (``curves.csv``, written by graf-curves), nothing recomputed: GRaF's
neighbor-feature mode ranked on validation (:func:`choose`, per regime), a method's budget by the studies' rule
(:func:`best_step` with :data:`graf.run.budgets.BUDGET_WITHIN_DB`), whether a curve still gains
(:func:`still_gaining`), and the main job's rule (:func:`leading_knn`).

The site (``docs_hooks/hooks.py``), ``scripts/choose_graf.py`` and the studies' budget test all read the curves
through this module, so they make the same choice.
"""

from __future__ import annotations

import math
from collections import defaultdict

from omegaconf import OmegaConf

from graf.app import config as app_config
from graf.errors import ConfigError, UserError
from graf.metrics.names import choice_figures
from graf.run.budgets import BUDGET_WITHIN_DB

GAIN_PER_DOUBLING_DB = 0.1  # a curve still gaining more than this per doubling of steps is extended (regime d30)
VALIDATION_FIGURES = choice_figures()  # (key, higher is better) of the choice rules' figures (graf.metrics.names)


def regimes_ready(
    rows: list[dict], modes: list[str], continues: dict[str, str] | None = None
) -> tuple[list[str], dict[str, list[str]]]:
    """``rows`` of curves.csv -> (the regimes where every one of ``modes`` has a point, so :func:`choose` can rank
    them; {regime: the modes still without a point} for the others, curves still in progress).  A regime of
    ``continues`` (it sends some of another regime's curves on to a larger budget) is neither: it makes no choice of
    its own (:func:`continued`)."""
    have = defaultdict(set)
    for r in rows:
        if r["method"] in modes and r["regime"] not in (continues or {}):
            have[r["regime"]].add(r["method"])
    ready = sorted(reg for reg, ms in have.items() if len(ms) == len(set(modes)))
    waiting = {reg: [m for m in modes if m not in ms] for reg, ms in sorted(have.items()) if reg not in ready}
    return ready, waiting


def curves_regimes() -> tuple:
    """(``conf/curves.yaml``'s regimes, the file's path)."""
    path = f"{app_config.CONF_DIR}/curves.yaml"
    return OmegaConf.load(path).regimes, path


def continued_regimes(regimes=None, path: str = "curves.yaml") -> dict[str, str]:
    """{regime: the regime it continues} from the ``continues`` keys of ``regimes`` (graf-curves' config, checked at
    its start), by default ``conf/curves.yaml``'s (the site's); one naming no other regime there stops with a
    :class:`~graf.errors.ConfigError` naming ``path``."""
    if regimes is None:
        regimes, path = curves_regimes()
    out = {name: str(r.continues) for name, r in regimes.items() if r.get("continues")}
    for name, parent in out.items():
        if parent not in regimes or parent == name:
            raise ConfigError(f"{path}: regimes.{name}.continues: {parent!r} is not another regime of the file")
    return out


def own_run_regimes() -> set[str]:
    """The regimes whose points are runs of their own (``each_point: own_run``): they read a study's budget or the
    main job's choice (:func:`leading_knn`), and take no part in ranking GRaF's modes."""
    return {name for name, r in curves_regimes()[0].items() if r.get("each_point") == "own_run"}


def _point(r: dict) -> dict:
    """A curves.csv row as the choice's tables hold it: regime, step, mode, the validation figures, reliance."""
    return {
        "regime": r["regime"],
        "step": int(r["step"]),
        "mode": r["method"],
        **{k: float(r[k]) for k, _ in VALIDATION_FIGURES},
        "reliance": float(r["val_reliance_db"] or "nan"),  # none: a method that reads no neighbors
    }


def ahead_label(t: dict) -> str:
    """A row of :func:`continued`'s table: the figures in which it is ahead of the choice ("none"; "" for the
    choice's own row), as the site and ``scripts/choose_graf.py`` print it."""
    return "" if t["point"] == "chosen" else ", ".join(k.removeprefix("val_") for k in t["ahead"]) or "none"


def continued(rows: list[dict], regime: str, parent_table: list[dict], chosen: str) -> list[dict]:
    """Beside the parent regime's choice, the curves ``regime`` continued: the chosen mode's row of the parent's
    table, then each continued mode's best point (validation PSNR) and last point, each with the figures in which
    it is ahead of the chosen row (``ahead``: e.g. ``["val_psnr"]``; empty: behind or level in all three).  The
    rule ranks at the largest step every mode reached, so a continuation reports; it does not choose."""
    ref = next(t for t in parent_table if t["mode"] == chosen)
    out = [{**{k: v for k, v in ref.items() if k != "mean_rank"}, "point": "chosen", "ahead": []}]
    for mode in dict.fromkeys(r["method"] for r in rows if r["regime"] == regime):
        pts = sorted((r for r in rows if r["regime"] == regime and r["method"] == mode), key=lambda r: int(r["step"]))
        best = max(pts, key=lambda r: float(r["val_psnr"]))
        for label, r in (("best", best), ("last", pts[-1])) if best is not pts[-1] else (("best and last", best),):
            t = _point(r)
            ahead = [k for k, higher in VALIDATION_FIGURES if (t[k] - ref[k]) * (1 if higher else -1) > 0]
            out.append({**t, "point": label, "ahead": ahead})
    return out


def choose_per_regime(
    rows: list[dict], modes: list[str], continues: dict[str, str] | None = None, skip: set[str] = frozenset()
) -> tuple[list[tuple[str | None, str, list[dict]]], dict, list[tuple[str, str, str, list[dict]]]]:
    """:func:`choose` in each regime every mode has reached and over those regimes together (regime None):
    ([(regime, chosen, table)], {regime in progress: its modes without a point}, [(continuing regime, the regime
    it continues, that regime's choice, :func:`continued`'s table)]), what the site and ``scripts/choose_graf.py``
    print.  ``continues``: {regime: the regime it continues} (:func:`continued_regimes`); ``skip``: regimes left
    out (:func:`own_run_regimes`)."""
    continues = continues or {}
    rows = [r for r in rows if r["regime"] not in skip]
    ready, waiting = regimes_ready(rows, modes, continues)
    out = []
    for regime in ready + [None] if ready else []:  # nothing ready (an own-run regime alone): no choice to print
        chosen, table = choose([r for r in rows if r["regime"] in ready and regime in (None, r["regime"])], modes)
        out.append((regime, chosen, table))
    choices = {regime: (chosen, table) for regime, chosen, table in out}
    beside = [
        (regime, parent, choices[parent][0], continued(rows, regime, choices[parent][1], choices[parent][0]))
        for regime, parent in sorted(continues.items())
        if parent in choices and any(r["regime"] == regime for r in rows)
    ]
    return out, waiting, beside


def choose(rows: list[dict], modes: list[str]) -> tuple[str, list[dict]]:
    """``rows`` of curves.csv -> (chosen mode, one record per (mode, regime) it compared).

    The rule: among ``modes``, at the largest step that every mode has reached in a regime, rank the modes on each
    validation figure (higher PSNR and SSIM, lower LPIPS is better); the chosen mode has the best mean rank over
    the figures of the regimes in ``rows``, ties broken by the higher mean PSNR."""
    by = defaultdict(dict)  # (regime, mode) -> step -> row
    for r in rows:
        if r["method"] in modes:
            by[(r["regime"], r["method"])][int(r["step"])] = r
    regimes = sorted({reg for reg, _ in by})
    if not regimes:
        raise UserError(f"curves: no rows of the modes {modes} in the curves")
    ranks, psnr, table = defaultdict(list), defaultdict(list), []
    for reg in regimes:
        missing = [m for m in modes if (reg, m) not in by]
        if missing:
            raise UserError(f"curves: regime {reg} has no points of {missing}")
        step = min(max(by[(reg, m)]) for m in modes)  # the largest step every mode reached
        common = [m for m in modes if step in by[(reg, m)]]
        if len(common) < len(modes):
            raise UserError(f"curves: regime {reg}: not every mode has a point at step {step}")
        for key, higher in VALIDATION_FIGURES:
            vals = {m: float(by[(reg, m)][step][key]) for m in modes}
            order = sorted(modes, key=lambda m: -vals[m] if higher else vals[m])
            for i, m in enumerate(order):
                ranks[m].append(i + 1)
        for m in modes:
            r = by[(reg, m)][step]
            psnr[m].append(float(r["val_psnr"]))
            table.append(_point(r))
    score = {m: sum(ranks[m]) / len(ranks[m]) for m in modes}
    chosen = min(modes, key=lambda m: (score[m], -sum(psnr[m]) / len(psnr[m])))
    for t in table:
        t["mean_rank"] = score[t["mode"]]
    return chosen, table


def best_step(rows: list[dict], method: str, regime: str | None = None, within_db: float = 0.0) -> int | None:
    """The budget rule of the studies: the smallest step of ``method``'s curve (in ``regime`` when given) whose
    validation PSNR is within ``within_db`` of the curve's best (0: the best point itself, the smaller step on a
    tie; regime ``cross_family_val`` takes 0.1 dB, its rule in docs/learning-curves.md), or None without points."""
    pts = curve(rows, method, regime)
    if not pts:
        return None
    top = max(p for _, p in pts)
    return min(s for s, p in pts if p >= top - within_db)


def curve(rows: list[dict], method: str, regime: str | None = None) -> list[tuple[int, float]]:
    """``method``'s (step, validation PSNR) points, by step, in ``regime`` when given."""
    return sorted(
        (int(r["step"]), float(r["val_psnr"]))
        for r in rows
        if r["method"] == method and (regime is None or r["regime"] == regime) and r.get("val_psnr") not in ("", None)
    )


def still_gaining(rows: list, method: str, regime: str, per_doubling_db: float = GAIN_PER_DOUBLING_DB) -> bool | None:
    """Whether ``method``'s curve in ``regime`` still gains more than ``per_doubling_db`` per doubling of steps
    between its last two points (gain / log2(step ratio)): the rule that extends a curve of regime
    ``cross_family_val`` from 10,000 to 30,000 steps.  None with fewer than two points."""
    pts = curve(rows, method, regime)
    if len(pts) < 2:
        return None
    (s0, p0), (s1, p1) = pts[-2], pts[-1]
    return (p1 - p0) / math.log2(s1 / s0) > per_doubling_db


def leading_knn(
    rows: list[dict], knn: dict, regime: str, within_db: float = BUDGET_WITHIN_DB
) -> tuple[dict | None, list]:
    """The main job's rule (``conf/experiment/graf_rfid_s23.yaml``), on the points of ``regime`` (curves.csv rows)
    and its KNN line (``knn``: curves' results.json ``knn[regime]``): the points that lead KNN in all three
    validation figures (higher PSNR and SSIM, lower LPIPS); of those, the highest validation PSNR, and among the
    points within ``within_db`` of it the fewest steps.  (the chosen point or None, every point with ``leads``)."""
    line = {k: knn.get(k.replace("_", "/", 1)) for k, _ in VALIDATION_FIGURES}
    if any(v is None for v in line.values()):
        raise UserError(f"curves: regime {regime} has no KNN line with PSNR, SSIM and LPIPS")
    table = []
    for r in rows:
        if r["regime"] != regime or r["val_psnr"] in ("", None):
            continue
        p = _point(r)
        p["leads"] = all(p[k] > line[k] if up else p[k] < line[k] for k, up in VALIDATION_FIGURES)
        table.append(p)
    table.sort(key=lambda p: (p["mode"], p["step"]))
    lead = [p for p in table if p["leads"]]
    if not lead:
        return None, table
    top = max(p["val_psnr"] for p in lead)
    return min((p for p in lead if p["val_psnr"] >= top - within_db), key=lambda p: (p["step"], -p["val_psnr"])), table
