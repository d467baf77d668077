"""Write the main job's headline tables into the README (between their headline markers) from the published
records ``sweeps/main_job/results.json`` and, where the README has its block, the accurate variant's
``sweeps/main_job_accurate/results.json``: ``python scripts/headline.py`` (``--check``: exit 1 if the README
differs).
The site's pages include the same table through ``<!-- gen: headline -->``; tests/test_docs_layout.py checks
that the README's is up to date."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from graf.reports.table import ACCURATE, HEADLINE, markers, with_headline

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str]) -> int:
    readme = ROOT / "README.md"
    text = readme.read_text()
    new = with_headline(text, json.loads((ROOT / HEADLINE).read_text()))
    if markers(ACCURATE)[0] in new:
        new = with_headline(new, json.loads((ROOT / ACCURATE).read_text()), ACCURATE)
    if "--check" in argv:
        return 0 if new == text else 1
    readme.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
