"""Compare the build test's table widths (``docs_hooks/site_checks.py``, no browser) with headless Chromium's.

    AUDIT=1 SITE=site bash scripts/site_screenshots.sh /tmp/audit
    python scripts/site_audit.py /tmp/audit/tables.json site

Prints, over every table of the built site, how far the estimated narrowest width is from Chromium's (the table's
min-content width) and the tables each finds wider than their column at 1,400 px (Chromium: hidden in
part behind a scroll bar), then any table where the two disagree by more than 8 px or on overflow.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # docs_hooks is a folder of the repository, not part of the package

from docs_hooks import site_checks  # noqa: E402


def main(audit: str, site: str) -> int:
    measured = json.loads(Path(audit).read_text())
    rows, off, both = [], [], {"chromium": set(), "estimate": set()}
    for t in measured:
        est = site_checks.page_tables((Path(site) / t["page"]).read_text())
        if t["index"] >= len(est):
            print(f"error: {t['page']}: Chromium saw table {t['index']}, the estimate has {len(est)}")
            return 1
        head, need, have = est[t["index"]]
        diff = need - t["narrowest"]
        rows.append(diff)
        key = (t["page"], t["index"])
        if t["scroll"] > t["client"]:
            both["chromium"].add(key)
        if need > have:
            both["estimate"].add(key)
        if abs(diff) > 8 or abs(have - (t["client"] - 32)) > 1:
            off.append(f"{t['page']} table {t['index']} ({head}): estimate {need:.0f} px of {have:.0f}, "
                       f"Chromium {t['narrowest']} px of {t['client'] - 32}")  # fmt: skip
    near = sorted(abs(d) for d in rows)[int(0.95 * (len(rows) - 1))]
    print(f"{len(rows)} tables: estimate - Chromium, narrowest width: median {statistics.median(rows):+.1f} px, "
          f"from {min(rows):+.1f} to {max(rows):+.1f} px; 95% within {near:.1f} px")  # fmt: skip
    for who, keys in both.items():
        print(f"behind a scroll bar by {who}: {len(keys)}: {sorted(keys)}")
    print("agree on overflow" if both["chromium"] == both["estimate"] else "DISAGREE on overflow")
    print("\n".join(off))
    return 0 if both["chromium"] == both["estimate"] else 1


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python scripts/site_audit.py TABLES_JSON SITE_DIR")
    sys.exit(main(sys.argv[1], sys.argv[2]))
