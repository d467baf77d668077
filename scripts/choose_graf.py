"""Choose GRaF's neighbor-feature mode from the learning curves, on validation figures only (the curves never
test).

The rule: among the GRaF modes, at the largest step that every mode has reached in a regime, rank the modes on
each validation figure (PSNR, SSIM, LPIPS; higher PSNR and SSIM, lower LPIPS is better); the chosen mode has
the best mean rank over the figures of the regimes considered, ties broken by the higher mean PSNR.  It prints
the choice per regime and over all regimes together (a regime where some mode has no point yet is named and
left out).  The 150-position studies took regime (b)'s choice, ``cross_family``; the paper-density studies take
regime (c)'s, ``cross_family_paper``; the main job takes regime (a)'s, ``rfid_sparse``.
The rule is :func:`graf.studies.published.choose`, applied per regime by ``choose_per_regime`` (the site's
table of the choice uses it too).

    python scripts/choose_graf.py [sweeps/learning_curves/curves.csv] [--modes pooled ray ray_knn ray_weights]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from graf.errors import UserError
from graf.studies.published import choose_per_regime


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
    try:
        choices, waiting = choose_per_regime(rows, args.modes)
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


if __name__ == "__main__":
    main()
