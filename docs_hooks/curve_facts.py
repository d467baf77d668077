"""The Learning curves page's facts of a regime (``<!-- gen: curve_facts REGIME -->``), generated from the records so
the page's prose never types a figure: the regime's KNN line (its ``knn/results.json``, the mean over its validation
scenes, as graf-curves draws it) and, per method of ``curves.csv``, the best validation PSNR and its step, the last
point, the slope between the last two points and the first step past KNN's line.

A value the records leave empty (``""`` in the csv: NeRF2 and RF-GS measure no reliance) prints as ``n/a``.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from mkdocs.exceptions import PluginError

from graf.metrics.names import choice_figures, curve_metrics
from graf.reports import published

CURVES = Path(__file__).resolve().parents[1] / "sweeps" / "learning_curves"


def figures() -> tuple[tuple[str, str, str, int, str], ...]:
    """curves.csv's column, the KNN record's key, the format, which way is better (1 higher, -1 lower, 0 neither)
    and the label, of each metric on the curves (the registry's, a plugin's included), then the reliance."""
    own = [(f"val_{m.name}", f"val/{m.name}", m.fmt, 1 if m.higher_is_better else -1, m.label) for m in curve_metrics()]
    return (*own, ("val_reliance_db", "val/reliance_db", "{:.2f}", 0, "reliance dB"))


def choice_columns() -> list[tuple[str, str, str, int, str]]:
    """The figures the choice rules compare with KNN's (:data:`graf.metrics.names.CHOICE_METRICS`)."""
    chosen = dict(choice_figures())
    return [f for f in figures() if f[0] in chosen]


def head() -> list[str]:
    past = " / ".join(f[4] for f in choice_columns())
    return ["method", "best PSNR (step)", "last step", *(f[4] for f in figures()),
            "dB per doubling (per decade), last two points", f"first step past KNN: {past}"]  # fmt: skip


def num(v) -> float | None:
    """A figure of the records, None where it is missing ("", None, NaN)."""
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(x) else x


def fmt(v, spec: str) -> str:
    """``v`` in ``spec`` (the registry's ``{:.2f}``, or a bare ``.2f``), n/a where it is missing."""
    x = num(v)
    return "n/a" if x is None else (spec.format(x) if "{" in spec else format(x, spec))


def _read(path: Path) -> str:
    if not path.is_file():
        raise PluginError(f"docs: {path} is missing: the page asks for the learning curves' facts")
    return path.read_text()


def knn_line(regime: str) -> tuple[dict, int | None]:
    """The regime's KNN line (the mean over its validation scenes) and its validation spectra (None: not recorded)."""
    res = json.loads(_read(CURVES / regime / "knn" / "results.json"))
    evals = res.get("evaluations") or [res]
    line = {}
    for _, key, _, _, _ in figures():
        v = [x for x in (num((e.get("metrics") or {}).get(key)) for e in evals) if x is not None]
        line[key] = sum(v) / len(v) if v else None
    n = [(e.get("splits") or {}).get("n_val") for e in evals]
    return line, None if None in n else sum(n)


def slope(pts: list[dict]) -> str:
    """The PSNR gain between the last two points, per doubling of steps (per decade in brackets)."""
    if len(pts) < 2 or None in (num(pts[-2]["val_psnr"]), num(pts[-1]["val_psnr"])):
        return "n/a"
    (a, b), (s, t) = [num(p["val_psnr"]) for p in pts[-2:]], [int(p["step"]) for p in pts[-2:]]
    return f"{(b - a) / math.log2(t / s):+.2f} ({(b - a) / math.log10(t / s):+.2f}), {s}-{t}"


def first_past(pts: list[dict], line: dict) -> str:
    """The first step past KNN's line in each choice figure (above it in PSNR and SSIM, below it in LPIPS; "never":
    no point is; "(not at N)": the last point, N, is not)."""
    out = []
    for col, key, _, better, _ in choice_columns():
        if line[key] is None:
            out.append("n/a")
            continue
        steps = [p["step"] for p in pts if num(p[col]) is not None and better * (num(p[col]) - line[key]) > 0]
        lost = f" (not at {pts[-1]['step']})" if steps and steps[-1] != pts[-1]["step"] else ""
        out.append(steps[0] + lost if steps else "never")
    return " / ".join(out)


def block(regime: str) -> str:
    """The regime's facts: a sentence for its KNN line and a table with a row per method (in curves.csv's order)."""
    rows = [r for r in csv.DictReader(_read(CURVES / "curves.csv").splitlines()) if r["regime"] == regime]
    if not rows:
        raise PluginError(f"docs: <!-- gen: curve_facts {regime} -->: curves.csv has no point of {regime}")
    line, n_val = knn_line(regime)
    body = []
    for method in dict.fromkeys(r["method"] for r in rows):
        pts = sorted((r for r in rows if r["method"] == method), key=lambda r: int(r["step"]))
        known = [p for p in pts if num(p["val_psnr"]) is not None]
        best = max(known, key=lambda p: num(p["val_psnr"]), default=None)
        best_s = f"{fmt(best['val_psnr'], '.2f')} ({best['step']})" if best else "n/a"
        last = [fmt(pts[-1].get(col), spec) for col, _, spec, _, _ in figures()]
        body.append([f"`{method}`", best_s, pts[-1]["step"], *last, slope(pts), first_past(pts, line)])
    units = {f"val/{m.name}": m.unit for m in curve_metrics()} | {"val/reliance_db": "dB"}
    knn = ", ".join(
        f"{label.removesuffix(' dB')} {fmt(line[key], spec)}{' ' + units[key] if units[key] else ''}"
        for _, key, spec, _, label in figures()
    )
    spectra = f"{n_val} validation spectra" if n_val is not None else "validation spectra not recorded"
    note = (
        f"*Generated from `sweeps/learning_curves/curves.csv` and `{regime}/knn/results.json`. Past KNN: above its "
        'line in PSNR and SSIM, below it in LPIPS; "(not at N)": the last point, N, is not past it.*'
    )
    return f"KNN's line ({spectra}): {knn}.\n\n{published.md(head(), body)}\n\n{note}"
