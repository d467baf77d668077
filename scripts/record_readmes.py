"""Rewrite the generated block of published study records' README.md (their tables and paired intervals, between
the graf-report markers) from each folder's own ``report.json``, ``rows.json`` and ``intervals.json``, without
reading the jobs again (:func:`graf.reports.readme.refresh`; ``graf-report runs=FOLDER readme_only=true`` does the
same for one folder):

    python scripts/record_readmes.py                      # every sweeps/*/ with a report.json and a README.md
    python scripts/record_readmes.py sweeps/bands_paper   # these folders (a README is made where there is none)
    python scripts/record_readmes.py --check              # exit 1, naming them, if a README's block is not current
"""

from __future__ import annotations

import sys
from pathlib import Path

from graf.errors import UserError
from graf.reports.readme import block, refresh, with_block

ROOT = Path(__file__).resolve().parents[1]


def folders(args: list[str]) -> list[Path]:
    if args:
        return [Path(a) for a in args]
    return [p.parent for p in sorted((ROOT / "sweeps").glob("*/report.json")) if (p.parent / "README.md").is_file()]


def main(argv: list[str]) -> int:
    check = "--check" in argv
    stale = []
    try:
        for folder in folders([a for a in argv if a != "--check"]):
            if not check:
                print(refresh(folder))
                continue
            readme = folder / "README.md"
            text = readme.read_text() if readme.is_file() else ""
            if with_block(text, block(folder), folder.name) != text:
                stale.append(str(readme))
    except UserError as e:
        print(f"record_readmes: {e}", file=sys.stderr)
        return 2
    for s in stale:
        print(f"{s}: its generated block differs from its record (python scripts/record_readmes.py rewrites it)")
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
