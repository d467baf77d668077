"""Choose GRaF's neighbor-feature mode from the learning curves, on validation figures only (the curves never
test).

The rule: among the GRaF modes, at the largest step that every mode has reached in a regime, rank the modes on
each validation figure (PSNR, SSIM, LPIPS; higher PSNR and SSIM, lower LPIPS is better); the chosen mode has
the best mean rank over the figures of the regimes considered, ties broken by the higher mean PSNR.  It prints
the choice per regime and over all regimes together: the studies (cross-scene, on simulated layouts) take
regime (b)'s choice, ``cross_family``, the regime they run in; the main job takes regime (a)'s, ``rfid_sparse``.

    python scripts/choose_graf.py [sweeps/learning_curves/curves.csv] [--modes pooled ray ray_knn ray_weights]
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

METRICS = (("val_psnr", True), ("val_ssim", True), ("val_lpips", False))


def choose(rows: list[dict], modes: list[str]) -> tuple[str, list[dict]]:
    """``rows`` of curves.csv -> (chosen mode, one record per (mode, regime) it compared)."""
    by = defaultdict(dict)  # (regime, mode) -> step -> row
    for r in rows:
        if r["method"] in modes:
            by[(r["regime"], r["method"])][int(r["step"])] = r
    regimes = sorted({reg for reg, _ in by})
    if not regimes:
        raise SystemExit(f"error: no rows of the modes {modes} in the curves")
    ranks, psnr, table = defaultdict(list), defaultdict(list), []
    for reg in regimes:
        missing = [m for m in modes if (reg, m) not in by]
        if missing:
            raise SystemExit(f"error: regime {reg} has no points of {missing}")
        step = min(max(by[(reg, m)]) for m in modes)  # the largest step every mode reached
        common = [m for m in modes if step in by[(reg, m)]]
        if len(common) < len(modes):
            raise SystemExit(f"error: regime {reg}: not every mode has a point at step {step}")
        for key, higher in METRICS:
            vals = {m: float(by[(reg, m)][step][key]) for m in modes}
            order = sorted(modes, key=lambda m: -vals[m] if higher else vals[m])
            for i, m in enumerate(order):
                ranks[m].append(i + 1)
        for m in modes:
            r = by[(reg, m)][step]
            psnr[m].append(float(r["val_psnr"]))
            table.append(
                {
                    "regime": reg,
                    "step": step,
                    "mode": m,
                    **{k: float(r[k]) for k, _ in METRICS},
                    "reliance": float(r["val_reliance_db"]),
                }
            )
    score = {m: sum(ranks[m]) / len(ranks[m]) for m in modes}
    chosen = min(modes, key=lambda m: (score[m], -sum(psnr[m]) / len(psnr[m])))
    for t in table:
        t["mean_rank"] = score[t["mode"]]
    return chosen, table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("curves", nargs="?", default="sweeps/learning_curves/curves.csv")
    ap.add_argument("--modes", nargs="+", default=["pooled", "ray", "ray_knn", "ray_weights"])
    args = ap.parse_args()
    path = Path(args.curves)
    if not path.is_file():
        sys.exit(f"error: {path}: no such curves file (run graf-curves first)")
    with path.open() as f:
        rows = list(csv.DictReader(f))
    regimes = sorted({r["regime"] for r in rows if r["method"] in args.modes})
    for regime in regimes + [None]:
        chosen, table = choose([r for r in rows if regime is None or r["regime"] == regime], args.modes)
        print(f"\n### {regime or 'all regimes together'}\n")
        print("| regime | step | mode | val PSNR | val SSIM | val LPIPS | val reliance dB | mean rank |")
        print("|---|---|---|---|---|---|---|---|")
        for t in table:
            print(
                f"| {t['regime']} | {t['step']} | {t['mode']} | {t['val_psnr']:.2f} | {t['val_ssim']:.3f} | "
                f"{t['val_lpips']:.3f} | {t['reliance']:.2f} | {t['mean_rank']:.2f} |"
            )
        print(f"\nchosen ({regime or 'all regimes together'}): {chosen}")


if __name__ == "__main__":
    main()
