"""Markdown views of the published study records in ``sweeps/``, nothing recomputed: a study's tables (its
``report.json`` and ``rows.json``, written by graf-report).

The site (``docs_hooks/hooks.py``) and the command-line view (``scripts/study_tables.py``) both read the records
through this module, so they show the same figures.  The choices read off the learning curves (GRaF's mode, the
studies' budgets, the main job's rule) are :mod:`graf.reports.choices`.
"""

from __future__ import annotations

from collections import defaultdict

from graf.reports.rows import TEST_FIGURES, matrices, seed_means, seeds_told  # TEST_FIGURES: the registry's
from graf.reports.table import fmt, md  # noqa: F401  (the views' markdown, read from here by the site and readme)

FRACTIONS = ("-", "none", "f05", "f10", "f20", "f50", "f100")


def reliance_matrix(rows: list[dict]) -> str:
    """Test reliance (dB) per trained-on x tested-on cell, from the rows (methods that measured it)."""
    rel = [r for r in rows if r.get("test/reliance_db") is not None and r.get("steps") != "0"]
    if not rel:
        return ""
    cols = sorted({r["eval_scene"] for r in rel})
    body = []
    for (method, trained), rs in sorted(_group(rel, ("method", "trained_on")).items()):
        cell = {r["eval_scene"]: r["test/reliance_db"] for r in rs}
        body.append([method, trained, *[fmt(cell.get(c), "{:.2f}") for c in cols]])
    told = seeds_told(r.get("n_seeds") or 1 for r in rel)
    return f"**reliance dB** (rows: trained on; columns: tested on; {told})\n\n" + md(
        ["method", "trained on", *cols], body
    )


def _group(rows: list[dict], keys: tuple[str, ...]) -> dict:
    out = defaultdict(list)
    for r in rows:
        out[tuple(r[k] for k in keys)].append(r)
    return out


def per_pair(rows: list[dict]) -> str:
    """Test PSNR per (trained on -> tested on) pair and L, for every method, from the rows."""
    rs = [r for r in rows if r.get("L") not in (None, "", "-") and not r.get("within_scene")]
    ls = sorted({int(r["L"]) for r in rs})
    body = []
    for (scene, method, trained), g in sorted(_group(rs, ("eval_scene", "method", "trained_on")).items()):
        by_l = {int(r["L"]): r.get("test/psnr") for r in g}
        body.append([scene, method, trained, *[fmt(by_l.get(x), "{:.2f}") for x in ls]])
    header = ["tested on", "method", "trained on", *[f"L = {x}" for x in ls]]
    told = seeds_told(r.get("n_seeds") or 1 for r in rs if r["steps"] != "0")
    return f"**PSNR per pair** (zero-shot, each test layout; {told})\n\n" + md(header, body)


def matrix(report: dict, rows: list[dict] | None = None) -> str:
    """The trained-on x tested-on tables of each metric, each cell the mean over its seeds: from ``rows`` (a
    record's rows.json) where given, else from report.json's ``matrix``."""
    mats = matrices(rows) if rows else report["matrix"]
    told = seeds_told(r["n_seeds"] for r in seed_means(rows) if r["steps"] != "0") if rows else "from report.json"
    out = []
    for _, name, f in TEST_FIGURES:
        cols = None
        body = []
        for method, mats_m in mats.items():
            m = mats_m[name]
            cols = m["cols"]
            for r, vals in zip(m["rows"], m["values"]):
                body.append([method, r, *[fmt(None if v != v else v, f) for v in vals]])
        out.append(
            f"**{name}** (rows: trained on; columns: tested on; {told})\n\n" + md(["method", "trained on", *cols], body)
        )
    if rows and reliance_matrix(rows):
        out.append(reliance_matrix(rows))
    return "\n\n".join(out)


def pairs(rows: list[dict]) -> str:
    """'conference_v1 -> v2/v3 and office_v1 -> v2/v3': the (trained on -> tested on) pairs the rows average."""
    by = {}
    for r in rows:
        if r.get("L") not in (None, "") and not r.get("within_scene") and r.get("trained_on") not in (None, "", "-"):
            by.setdefault(str(r["trained_on"]), set()).add(str(r["eval_scene"]).rsplit("_", 1)[-1])
    return " and ".join(f"{t} -> {'/'.join(sorted(v))}" for t, v in sorted(by.items()))


def vs_l(report: dict, rows: list[dict]) -> str:
    data = report["vs_L"]
    ls = sorted({int(x) for pts in data.values() for x in pts})
    out = []
    for _, name, f in TEST_FIGURES:
        body = [[m, *[fmt(pts.get(str(x), {}).get(name), f) for x in ls]] for m, pts in data.items()]
        out.append(f"**{name}** vs L (mean over {pairs(rows)})\n\n" + md(["method", *[f"L = {x}" for x in ls]], body))
    return "\n\n".join(out)


def unseen(rows: list[dict]) -> str:
    out = []
    keys = sorted({(r["eval_scene"], r["train_band"]) for r in rows if r["steps"] != "0"})
    told = seeds_told(r.get("n_seeds") or 1 for r in rows if r["steps"] != "0")
    for scene, band in keys:
        sub = [r for r in rows if r["eval_scene"] == scene and r["train_band"] in (band, "-")]
        for ft, title in (("none", "zero-shot"), ("f20", "fine-tuned on 20%")):
            body = [
                [r["method"], r["n_test"], r["steps"], *[fmt(r.get(k), f) for k, _, f in TEST_FIGURES]]
                for r in sorted(sub, key=lambda r: r["method"])
                if r["finetune"] in ((ft, "zero-shot", "-") if ft == "none" else (ft, "-"))
            ]
            out.append(
                f"**{scene}**, models trained at {band}, {title} (test neighbors: "
                f"{'the whole training split' if ft == 'none' else 'the measured 20%'}; {told})\n\n"
                + md(["method", "test spectra", "steps", *[n for _, n, _ in TEST_FIGURES]], body)
            )
        by = defaultdict(dict)
        for r in sub:
            if r["steps"] != "0":
                by[r["method"]]["none" if r["finetune"] == "zero-shot" else r["finetune"]] = r.get("test/psnr")
        fr = [x for x in FRACTIONS[1:] if any(x in v for v in by.values())]
        out.append(
            f"PSNR vs fine-tuned fraction, **{scene}** (models trained at {band}; {told})\n\n"
            + md(
                ["method", *["zero-shot" if x == "none" else x for x in fr]],
                [[m, *[fmt(v.get(x), "{:.2f}") for x in fr]] for m, v in sorted(by.items())],
            )
        )
    return "\n\n".join(out)


def density(report: dict, rows: list[dict]) -> str:
    """Per scene: each method's test PSNR (reliance dB) and LPIPS against the survey (fraction of the training
    split measured, trained from scratch on it; its spacing: the median nearest-neighbor distance of the
    measured positions), and the largest spacing at which each method reaches X dB (report.json)."""
    out = []
    told = seeds_told(r.get("n_seeds") or 1 for r in rows if r["steps"] != "0")
    for scene in sorted({r["eval_scene"] for r in rows}):
        sub = [r for r in rows if r["eval_scene"] == scene]
        fr = [x for x in FRACTIONS if any(r["finetune"] == x for r in sub)]
        spacing = {r["finetune"]: r.get("spacing_m") for r in sub}
        head = ["method", *[f"{x} ({fmt(spacing.get(x) and spacing[x] * 100, '{:.1f}')} cm)" for x in fr]]
        by = defaultdict(dict)
        for r in sub:
            by[r["method"]][r["finetune"]] = r
        for key, name, f, rel in (
            ("test/psnr", "PSNR (reliance dB)", "{:.2f}", True),
            ("test/lpips", "LPIPS", "{:.3f}", False),
        ):
            body = []
            for m, cells in sorted(by.items()):
                row = [m]
                for x in fr:
                    r = cells.get(x) or {}
                    v = fmt(r.get(key), f)
                    if rel and r.get("test/reliance_db") is not None:
                        v += f" ({r['test/reliance_db']:.1f})"
                    row.append(v)
                body.append(row)
            out.append(
                f"**{scene}**: test {name} against the survey (fraction measured, its spacing; {told})\n\n"
                + md(head, body)
            )
        answer = (report.get("spacing_for_psnr") or {}).get(scene) or {}
        if answer:
            th = sorted({t for v in answer.values() for t in v}, key=float)
            body = [[m, *[fmt(v.get(t) and v[t] * 100, "{:.1f}") for t in th]] for m, v in sorted(answer.items())]
            out.append(
                f"**{scene}**: the largest survey spacing (cm) at which each method reaches X dB (- : not reached)\n\n"
                + md(["method", *[f"{t} dB" for t in th]], body)
            )
    return "\n\n".join(out)


def bands(report: dict) -> str:
    out = []
    for m, d in report["band_matrix"].items():
        body = [[r, *[fmt(v if v == v else None, "{:.2f}") for v in vals]] for r, vals in zip(d["rows"], d["psnr"])]
        out.append(
            f"**{m}**: test PSNR (rows: train band; columns: test band)\n\n" + md(["train \\ test", *d["cols"]], body)
        )
    return "\n\n".join(out)


def study_tables(report: dict, rows: list[dict]) -> list[str]:
    """Every table a study's record holds, by the keys of its ``report.json``: a train x test matrix, figures
    against L (and per pair), against the survey's density or the fine-tuned fraction, a band matrix."""
    rows = seed_means(rows)  # a cell's figure is the mean over its seeds, never one seed's run
    parts = []
    if "matrix" in report:
        parts.append(matrix(report, rows))
    if "vs_L" in report:
        parts += [vs_l(report, rows), per_pair(rows)]
    if "vs_spacing" in report:  # the density study: surveys trained from scratch, not fine-tuned fractions
        parts.append(density(report, rows))
    elif "vs_fraction" in report:
        parts.append(unseen(rows))
    if "band_matrix" in report:
        parts.append(bands(report))
    return parts
