"""Choose GRaF's neighbor-feature mode from the learning curves, on validation figures only (the curves never
test).

The rule: among the GRaF modes, at the largest step that every mode has reached in a regime, rank the modes on
each validation figure (PSNR, SSIM, LPIPS; higher PSNR and SSIM, lower LPIPS is better); the chosen mode has
the best mean rank over the figures of the regimes considered, ties broken by the higher mean PSNR.  It prints
the choice per regime and over all regimes together (a regime where some mode has no point yet is named and
left out).  A regime that ``continues`` another in ``conf/curves.yaml`` (some of its curves sent on to a larger
budget) makes no choice of its own: beside the other's choice it prints the chosen mode's point and each continued
curve's best and last points, with the figures in which each is ahead of the choice.  The 150-position studies
took regime (b)'s choice, ``cross_family``; the paper-density studies take regime (c)'s, ``cross_family_paper``,
then (d)'s, ``cross_family_val``; the main job takes regime (a)'s, ``rfid_sparse``.
The rule is :func:`graf.reports.choices.choose`, applied per regime by ``choose_per_regime`` (the site's
table of the choice uses it too).

Options: ``--regime R`` only that regime; ``--max-step N`` only the points at or below N steps (the main job's
choice within its time: ``--regime rfid_sparse --max-step 300``); ``--within-db D`` prints each method's budget,
the smallest step within D dB of its curve's best validation PSNR, and whether the curve still gains more than
0.1 dB per doubling of steps (the rule of regime ``cross_family_val``: then it goes on to 30,000).

``--leads-knn REGIME`` applies the main job's rule instead (:func:`graf.reports.choices.leading_knn`, stated in
``conf/experiment/graf_rfid_s23.yaml``): of the points of REGIME that lead its KNN line in all three validation
figures, the highest validation PSNR (within 0.1 dB: the fewest steps); the KNN line is read from the
``results.json`` beside the curves file.

    python scripts/choose_graf.py [sweeps/learning_curves/curves.csv] [--modes pooled ray ray_knn ray_weights]
    python scripts/choose_graf.py --leads-knn main_job
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from graf.errors import UserError
from graf.reports.choices import (
    GAIN_PER_DOUBLING_DB,
    ahead_label,
    best_step,
    choose_per_regime,
    continued_regimes,
    leading_knn,
    own_run_regimes,
    still_gaining,
)
from graf.run.budgets import BUDGET_WITHIN_DB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("curves", nargs="?", default="sweeps/learning_curves/curves.csv")
    ap.add_argument("--modes", nargs="+", default=["pooled", "ray", "ray_knn", "ray_weights"])
    ap.add_argument("--regime", default=None, help="only this regime")
    ap.add_argument("--max-step", type=int, default=None, help="only the points at or below this many steps")
    ap.add_argument(
        "--within-db",
        type=float,
        default=None,
        help=f"print each method's budget within this many dB (the studies' rule: {BUDGET_WITHIN_DB})",
    )
    ap.add_argument("--leads-knn", default=None, metavar="REGIME", help="the main job's rule on this regime")
    args = ap.parse_args()
    path = Path(args.curves)
    if not path.is_file():
        sys.exit(f"error: {path}: no such curves file (run graf-curves first)")
    with path.open() as f:
        rows = list(csv.DictReader(f))
    if args.leads_knn:
        sys.exit(main_job_choice(rows, path, args.leads_knn))
    continues = continued_regimes()
    # a regime that continues another is reported beside that one's choice: --regime of it keeps both
    regimes = None if args.regime is None else {args.regime, continues.get(args.regime, args.regime)}
    rows = [
        r
        for r in rows
        if (regimes is None or r["regime"] in regimes) and (args.max_step is None or int(r["step"]) <= args.max_step)
    ]
    try:
        choices, waiting, beside = choose_per_regime(rows, args.modes, continues, own_run_regimes())
    except UserError as e:
        print(f"error: {path}: {e}", file=sys.stderr)
        sys.exit(2)
    for regime, missing in waiting.items():
        print(f"{regime}: in progress, no choice yet (no point of {', '.join(missing)})")
    for regime, chosen, table in choices:
        print(f"\n### {regime or 'all regimes together'}\n")
        print("| regime | step | mode | val PSNR | val SSIM | val LPIPS | val reliance dB | mean rank |")
        print("|---|---|---|---|---|---|---|---|")
        for t in table:
            print(
                f"| {t['regime']} | {t['step']} | {t['mode']} | {t['val_psnr']:.2f} | {t['val_ssim']:.3f} | "
                f"{t['val_lpips']:.3f} | {t['reliance']:.2f} | {t['mean_rank']:.2f} |"
            )
        print(f"\nchosen ({regime or 'all regimes together'}): {chosen}")
    for regime, parent, chosen, table in beside:
        print(f"\n### {regime}: continues {parent} (no choice of its own; beside {parent}'s choice, {chosen})\n")
        print("| regime | step | mode | point | val PSNR | val SSIM | val LPIPS | ahead of the choice in |")
        print("|---|---|---|---|---|---|---|---|")
        for t in table:
            print(
                f"| {t['regime']} | {t['step']} | {t['mode']} | {t['point']} | {t['val_psnr']:.2f} | "
                f"{t['val_ssim']:.3f} | {t['val_lpips']:.3f} | {ahead_label(t)} |"
            )
    if args.within_db is not None:
        print(f"\n### budgets: the smallest step within {args.within_db} dB of the curve's best validation PSNR\n")
        gain = f"still gaining > {GAIN_PER_DOUBLING_DB} dB per doubling"
        print(f"| regime | method | budget (steps) | last step | {gain} |")
        print("|---|---|---|---|---|")
        for regime in sorted({r["regime"] for r in rows}):
            for m in sorted({r["method"] for r in rows if r["regime"] == regime and r["val_psnr"] not in ("", None)}):
                last = max(int(r["step"]) for r in rows if r["regime"] == regime and r["method"] == m)
                gaining = still_gaining(rows, m, regime)
                print(
                    f"| {regime} | {m} | {best_step(rows, m, regime, args.within_db)} | {last} | "
                    f"{'n/a' if gaining is None else 'yes' if gaining else 'no'} |"
                )


def main_job_choice(rows: list[dict], path: Path, regime: str) -> int:
    """Print the main job's rule on ``regime`` (every point, whether it leads KNN in all three figures, the choice)."""
    knn = json.loads((path.parent / "results.json").read_text()).get("knn", {}).get(regime)
    if knn is None:
        print(f"error: {path.parent / 'results.json'}: no KNN line of regime {regime}", file=sys.stderr)
        return 2
    try:
        chosen, table = leading_knn(rows, knn, regime)
    except UserError as e:
        print(f"error: {path}: {e}", file=sys.stderr)
        return 2
    print(f"### {regime}: the main job's rule (KNN: PSNR {knn['val/psnr']:.2f}, SSIM {knn['val/ssim']:.3f}, "
          f"LPIPS {knn['val/lpips']:.3f})\n")  # fmt: skip
    print("| mode | step | val PSNR | val SSIM | val LPIPS | leads KNN in all three |")
    print("|---|---|---|---|---|---|")
    for t in table:
        print(f"| {t['mode']} | {t['step']} | {t['val_psnr']:.2f} | {t['val_ssim']:.3f} | {t['val_lpips']:.3f} | "
              f"{'yes' if t['leads'] else 'no'} |")  # fmt: skip
    none = "\nchosen: none leads KNN in all three"
    print(f"\nchosen: {chosen['mode']} at {chosen['step']} steps" if chosen else none)
    return 0


if __name__ == "__main__":
    main()
