"""Bring the published records under ``sweeps/`` to the current record rules (per-spectrum files, seeds,
intervals), from what each record holds (nothing is re-run, nothing typed):

- ``scene`` names the scenes the model was trained on (``train_scenes`` joined by ``+``); records written before
  named the headline's test scene there.
- An empty target (no path: every pixel 0) is left out of every mean and counted (``test/n_empty``), its
  per-spectrum values NaN.  Records written before scored it, at PSNR's 100 dB cap.  Their per-spectrum files
  keep no target, so an empty target is recognised as one that *every* method of the job reproduced to PSNR's
  cap (MSE below 1e-9): a mix of neighbor spectra or a trained field matches a non-empty 90 x 360 spectrum to that
  precision never (no such row exists in any record but those of the outdoor scene's two empty positions).
  The job's means (the model's, each baseline's, each evaluation's) are then recomputed from the per-spectrum
  rows of the spectra left.

Usage: ``python scripts/upgrade_records.py [sweeps] [--check]`` (``--check``: say what would change, write
nothing).  Running it again changes nothing.
"""

from __future__ import annotations

import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from graf.io import atomic_write_json
from graf.metrics.names import METRIC_NAMES
from graf.run.per_spectrum import read_per_spectrum, write_per_spectrum

CAP = 100.0 - 1e-6


def _key(root: Path, f: Path, r: dict, scene: str) -> tuple:
    """Where a test spectrum's target is the same: the study folder, the test scene and its band."""
    band = next((e.get("band_hz") for e in r.get("evaluations") or [] if e["eval_scene"] == scene), r.get("band_hz"))
    return f.relative_to(root).parts[0], scene, band


def _rows(f: Path, r: dict) -> list[dict]:
    p = f.parent / (r.get("per_spectrum") or "-")
    return read_per_spectrum(p) if r.get("per_spectrum") and p.is_file() else []


def empty_targets(root: Path, files: list[Path]) -> dict[tuple, set[int]]:
    """``{(study, test scene, band): ids}`` of the targets some method of some job of the study reproduced to
    PSNR's cap with MSE below 1e-9, or that an upgraded or newer record marks NaN."""
    out = defaultdict(set)
    for f in files:
        r = json.loads(f.read_text())
        for x in _rows(f, r):
            if math.isnan(x["psnr"]) or (x["psnr"] >= CAP and x["mse"] < 1e-9):
                out[_key(root, f, r, x["eval_scene"])].add(x["id"])
    return out


def means(rows: list[dict], scene: str, method: str) -> dict:
    mine = [r for r in rows if r["eval_scene"] == scene and r["method"] == method]
    kept = [r for r in mine if not math.isnan(r["psnr"])]
    out = {f"test/{m}": float(np.mean([r[m] for r in kept])) if kept else None for m in METRIC_NAMES}
    out["test/n_empty"] = float(len(mine) - len(kept))
    return out


def _remean(r: dict, rows: list[dict], empties: dict[str, set[int]]) -> list[str]:
    """Recompute every evaluation's means (the model's and its baselines') from ``rows``."""
    said = []
    evaluations = r.get("evaluations") or [{"eval_scene": r["eval_scene"], "metrics": r["metrics"],
                                           "baselines": r.get("baselines") or {}}]  # fmt: skip
    for e in evaluations:
        scene, old = e["eval_scene"], e["metrics"].get("test/psnr")
        e["metrics"].update(means(rows, scene, r["method"]))
        for name, b in (e.get("baselines") or {}).items():
            b["metrics"].update(means(rows, scene, name))
        if empties.get(scene):
            new, ids = e["metrics"]["test/psnr"], sorted(empties[scene])
            said.append(f"{scene}: {len(ids)} empty {ids}; {r['method']} PSNR {old:.3f} -> {new:.3f}")
    first = (
        evaluations[0]
        if not r.get("evaluations")
        else next((e for e in r["evaluations"] if e["eval_scene"] == r["eval_scene"]), None)
    )
    if first is not None:
        r["metrics"] = first["metrics"]
        if r.get("baselines"):
            r["baselines"] = first["baselines"]
    return said


def upgrade(root: Path, f: Path, known: dict, write: bool) -> list[str]:
    r = json.loads(f.read_text())
    said = []
    if r.get("train_scenes") and r.get("scene") != "+".join(r["train_scenes"]):
        said.append(f"scene {r.get('scene')} -> {'+'.join(r['train_scenes'])}")
        r["scene"] = "+".join(r["train_scenes"])
    rows = _rows(f, r)
    scenes = {x["eval_scene"] for x in rows}
    empties = {
        s: {x["id"] for x in rows if x["eval_scene"] == s} & known.get(_key(root, f, r, s), set()) for s in scenes
    }
    fresh = [x for x in rows if x["id"] in empties[x["eval_scene"]] and not math.isnan(x["psnr"])]
    if fresh:
        for x in fresh:
            x.update({m: float("nan") for m in METRIC_NAMES})
        said += _remean(r, rows, empties)
        if write:
            write_per_spectrum(f.parent / r["per_spectrum"], rows)
    elif rows and "test/n_empty" not in r.get("metrics", {}):  # none empty: the means stand, the count is 0
        for e in [r, *(r.get("evaluations") or [])]:
            for m in [e["metrics"], *(b["metrics"] for b in (e.get("baselines") or {}).values())]:
                m["test/n_empty"] = 0.0
        said.append("test/n_empty = 0 recorded")
    if said and write:
        atomic_write_json(f, r)
    return said


def main(argv: list[str]) -> int:
    check = "--check" in argv
    args = [a for a in argv if a != "--check"]
    root = Path(args[0] if args else "sweeps")
    files = sorted(root.rglob("results.json"))
    known = empty_targets(root, files)
    for key, ids in sorted(known.items(), key=str):
        print(f"empty targets {key}: {sorted(ids)}")
    n = 0
    for f in files:
        said = upgrade(root, f, known, write=not check)
        if said:
            n += 1
            print(f"{f.relative_to(root)}: " + "; ".join(said))
    print(f"{n} record(s) {'would change' if check else 'changed'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
