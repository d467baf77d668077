"""Compact markdown views of a published study, for its README section: read from the study's report.json and
rows.json (written by graf-report), nothing recomputed (the tables are :func:`graf.reports.published.study_tables`,
the same the site shows).

    python scripts/study_tables.py sweeps/cross_scene_matrix      # train x test matrix per metric
    python scripts/study_tables.py sweeps/neighbor_count         # metric vs L per method
    python scripts/study_tables.py sweeps/unseen_layouts          # seed Tables 1-4 shape, metric vs fraction
    python scripts/study_tables.py sweeps/bands                   # train band x test band (PSNR)
    python scripts/study_tables.py sweeps/density                 # metric vs the survey, spacing for X dB
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from graf.reports.published import study_tables


def main() -> None:
    folder = Path(sys.argv[1])
    report = json.loads((folder / "report.json").read_text())
    rows = json.loads((folder / "rows.json").read_text())["rows"]
    for table in study_tables(report, rows):
        print(table)


if __name__ == "__main__":
    main()
