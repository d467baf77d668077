"""Rewrite the generated block of published study records' README.md (their tables and paired intervals, between
the graf-report markers) from each folder's own ``report.json``, ``rows.json`` and ``intervals.json``, without
reading the jobs again (:func:`graf.reports.readme.block`; ``graf-report runs=FOLDER readme_only=true`` does the
same for one folder), and the main job's table in ``sweeps/main_job/README.md`` from its ``results.json``
(:func:`graf.reports.table.with_headline`):

    python scripts/record_readmes.py                      # the main job, every sweeps/*/ with report.json + README
    python scripts/record_readmes.py sweeps/bands_paper   # these folders (a README is made where there is none)
    python scripts/record_readmes.py --check              # exit 1, naming them, if a README's block is not current
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from graf.errors import UserError
from graf.io import atomic_write_text
from graf.reports.readme import block, with_block
from graf.reports.table import HEADLINE, with_headline

ROOT = Path(__file__).resolve().parents[1]
MAIN_JOB = ROOT / "sweeps" / "main_job" / "README.md"


def main_job() -> tuple[str, str]:
    """(the main job's README, the same with its table generated from its ``results.json``)."""
    text = MAIN_JOB.read_text()
    return text, with_headline(text, json.loads((ROOT / HEADLINE).read_text()))


def folders(args: list[str]) -> list[Path]:
    if args:
        return [Path(a) for a in args]
    return [p.parent for p in sorted((ROOT / "sweeps").glob("*/report.json")) if (p.parent / "README.md").is_file()]


def stale_or_write(readme: Path, old: str, new: str, check: bool) -> bool:
    """Whether ``readme`` is stale (``check``), else write ``new`` over it when it differs from ``old``."""
    if check or old == new:
        return check and old != new
    atomic_write_text(readme, new)
    return False


def main(argv: list[str]) -> int:
    check = "--check" in argv
    args = [a for a in argv if a != "--check"]
    stale = []
    try:
        if not args and stale_or_write(MAIN_JOB, *main_job(), check):
            stale.append(str(MAIN_JOB))
        for folder in folders(args):
            readme = folder / "README.md"
            text = readme.read_text() if readme.is_file() else ""
            if stale_or_write(readme, text, with_block(text, block(folder), folder.name, str(readme)), check):
                stale.append(str(readme))
            elif not check:
                print(readme)
    except UserError as e:
        print(f"record_readmes: {e}", file=sys.stderr)
        return 2
    for s in stale:
        print(f"{s}: its generated block differs from its record (python scripts/record_readmes.py rewrites it)")
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
