"""Compact markdown views of a published study, for its README section: read from the study's report.json and
rows.json (written by graf-report), nothing recomputed.

    python scripts/study_tables.py sweeps/cross_scene_matrix      # train x test matrix per metric
    python scripts/study_tables.py sweeps/neighbor_count         # metric vs L per method
    python scripts/study_tables.py sweeps/unseen_layouts          # seed Tables 1-4 shape, metric vs fraction
    python scripts/study_tables.py sweeps/bands                   # train band x test band (PSNR)
    python scripts/study_tables.py sweeps/density                 # metric vs the survey, spacing for X dB
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

METRICS = (
    ("test/mse", "MSE", "{:.4f}"),
    ("test/lpips", "LPIPS", "{:.3f}"),
    ("test/psnr", "PSNR", "{:.2f}"),
    ("test/ssim", "SSIM", "{:.3f}"),
)
FRACTIONS = ("-", "none", "f05", "f10", "f20", "f50", "f100")


def md(header: list[str], body: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in body]
    return "\n".join(lines)


def fmt(v, f: str) -> str:
    return "-" if v is None else f.format(v)


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
    return "**reliance dB** (rows: trained on; columns: tested on)\n\n" + md(["method", "trained on", *cols], body)


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
    return "**PSNR per pair** (zero-shot, each test layout)\n\n" + md(header, body)


def matrix(report: dict, rows: list[dict] | None = None) -> str:
    out = []
    for _, name, f in METRICS:
        cols = None
        body = []
        for method, mats in report["matrix"].items():
            m = mats[name]
            cols = m["cols"]
            for r, vals in zip(m["rows"], m["values"]):
                body.append([method, r, *[fmt(v, f) for v in vals]])
        out.append(f"**{name}** (rows: trained on; columns: tested on)\n\n" + md(["method", "trained on", *cols], body))
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
    for _, name, f in METRICS:
        body = [[m, *[fmt(pts.get(str(x), {}).get(name), f) for x in ls]] for m, pts in data.items()]
        out.append(f"**{name}** vs L (mean over {pairs(rows)})\n\n" + md(["method", *[f"L = {x}" for x in ls]], body))
    return "\n\n".join(out)


def unseen(rows: list[dict]) -> str:
    out = []
    keys = sorted({(r["eval_scene"], r["train_band"]) for r in rows if r["steps"] != "0"})
    for scene, band in keys:
        sub = [r for r in rows if r["eval_scene"] == scene and r["train_band"] in (band, "-")]
        for ft, title in (("none", "zero-shot"), ("f20", "fine-tuned on 20%")):
            body = [
                [r["method"], r["n_test"], r["steps"], *[fmt(r.get(k), f) for k, _, f in METRICS]]
                for r in sorted(sub, key=lambda r: r["method"])
                if r["finetune"] in ((ft, "zero-shot", "-") if ft == "none" else (ft, "-"))
            ]
            out.append(
                f"**{scene}**, models trained at {band}, {title} (test neighbors: "
                f"{'the whole training split' if ft == 'none' else 'the measured 20%'})\n\n"
                + md(["method", "test spectra", "steps", *[n for _, n, _ in METRICS]], body)
            )
        by = defaultdict(dict)
        for r in sub:
            if r["steps"] != "0":
                by[r["method"]]["none" if r["finetune"] == "zero-shot" else r["finetune"]] = r.get("test/psnr")
        fr = [x for x in FRACTIONS[1:] if any(x in v for v in by.values())]
        out.append(
            f"PSNR vs fine-tuned fraction, **{scene}** (models trained at {band})\n\n"
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
        ):  # noqa: E501
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
                f"**{scene}**: test {name} against the survey (fraction measured, its spacing)\n\n" + md(head, body)
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


def main() -> None:
    folder = Path(sys.argv[1])
    report = json.loads((folder / "report.json").read_text())
    rows = json.loads((folder / "rows.json").read_text())["rows"]
    if "matrix" in report:
        print(matrix(report, rows))
    if "vs_L" in report:
        print(vs_l(report, rows))
        print(per_pair(rows))
    if "vs_spacing" in report:  # the density study: surveys trained from scratch, not fine-tuned fractions
        print(density(report, rows))
    elif "vs_fraction" in report:
        print(unseen(rows))
    if "band_matrix" in report:
        print(bands(report))


if __name__ == "__main__":
    main()
