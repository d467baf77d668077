"""graf-bench's outputs: each row's ratios to its scene's GRaF row, the table (bench.md) and results.json."""

from __future__ import annotations

import math
from pathlib import Path

from graf.io import atomic_write_bytes, atomic_write_json

GRAF_METHODS = ("graf", "graf-residual")
BASE_PRESET = "graf"


# ---------------------------------------------------------------------------------------------- report
def add_ratios(rows: list[dict]) -> dict:
    """Fill each row's ratios to its scene's ratio base (module doc); returns ``{scene: base preset}``."""
    bases = {}
    for r in rows:
        s = r["scene"]
        if s in bases:
            continue
        ok = [x for x in rows if x["scene"] == s and not x.get("error") and x.get("infer_s_per_spectrum")]
        base = next((x for x in ok if x["preset"] == BASE_PRESET), None) or next(
            (x for x in ok if x["method"] in GRAF_METHODS), None
        )
        bases[s] = base
    for r in rows:
        base = bases[r["scene"]]
        for key, ratio in (
            ("infer_s_per_spectrum", "infer_ratio_to_graf"),
            ("train_s_per_step", "train_ratio_to_graf"),
        ):
            v, b = r.get(key), (base or {}).get(key)
            r[ratio] = round(v / b, 4) if v is not None and b and not r.get("error") else None
    return {s: (b["preset"] if b else None) for s, b in bases.items()}


def fmt(v, spec: str = ".4g", none: str = "-") -> str:
    """``v`` in ``spec``; ``none`` for None or NaN."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return none
    return format(v, spec)


def _headline(result: dict) -> str:
    """The line above the table: where and how the rows were measured."""
    return (
        f"graf-bench on {result['device']} ({result['device_type']}, {result['threads']} threads, torch "
        f"{result['torch']}, precision {result.get('precision', '32')}): median of {result['spectra_timed']} "
        f"spectra and of {result['train_steps_timed']} "
        f"training steps (warm-up: {result['warmup']}); peak memory: {result['memory']}; "
        "ratios: to the scene's GRaF row (paper size where present); load: cores other processes used while the "
        "row's inference / training was timed; trusted: no where that load or the spread of repeated timings "
        f"passed its limit ({result.get('disturbance_limits')})."
        + (
            " Each row's spectra timed again beside a competing single-threaded process (slowdown = beside / quiet)."
            if result.get("compete")
            else ""
        )
    )


def markdown(result: dict) -> str:
    """The table of ``result["rows"]`` with a line on how it was measured."""
    head = _headline(result)
    cols = [
        "scene",
        "preset",
        "method",
        "samples/ray",
        "s/spectrum",
        "× GRaF",
        "s/step",
        "rays/step",
        "rays/s",
        "× GRaF",
        "peak MB train",
        "peak MB infer",
        "parameters",
        "checkpoint MB",
        "load (cores)",
        "trusted",
    ]
    compete = bool(result.get("compete"))
    if compete:
        cols += ["s/spectrum beside a busy process", "slowdown", "s/step beside a busy process", "slowdown"]
    lines = [head, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in result["rows"]:
        if r.get("error"):
            cells = [r["scene"], r["preset"], r.get("method") or "-", f"error: {r['error']}"] + [""] * (len(cols) - 4)
        else:
            cells = [
                r["scene"],
                r["preset"],
                r["method"],
                fmt(r["samples_per_ray"], "g"),
                fmt(r["infer_s_per_spectrum"]),
                fmt(r["infer_ratio_to_graf"], ".3g"),
                fmt(r["train_s_per_step"]),
                fmt(r.get("train_rays_per_step"), ","),
                fmt(r["train_rays_per_s"], ",.0f"),
                fmt(r["train_ratio_to_graf"], ".3g"),
                fmt(r["peak_mb_train"], ".1f"),
                fmt(r["peak_mb_infer"], ".1f"),
                fmt(r["parameters"], ","),
                fmt(r["checkpoint_mb"], ".2f"),
                "/".join(fmt(r.get(f"{p}_load_cores"), ".2f") for p in ("infer", "train")),
                "no: " + "; ".join(r["disturbances"]) if r.get("disturbed") else "yes",
            ]
            if compete:
                cells += [fmt(r.get("infer_s_per_spectrum_loaded")), fmt(r.get("infer_slowdown"), ".3g")]
                cells += [fmt(r.get("train_s_per_step_loaded")), fmt(r.get("train_slowdown"), ".3g")]
        lines.append("| " + " | ".join(str(c).replace("|", "/") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def write_result(out: Path, result: dict) -> None:
    """The ratios filled in, results.json and bench.md rewritten (atomically)."""
    result["ratio_base"] = add_ratios(result["rows"])
    atomic_write_json(out / "results.json", result)
    atomic_write_bytes(out / "bench.md", markdown(result).encode())
