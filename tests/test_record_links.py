"""Records one click away (docs_hooks/record_links.py): every record path a page cites is a link that resolves, into
the clone the site was built in (served from the repository's root) or, published, into the repository."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from docs_hooks import record_links

ROOT = Path(__file__).resolve().parents[1]


def test_a_cited_record_path_becomes_a_link_and_a_missing_one_is_reported(monkeypatch):
    monkeypatch.delenv("GRAF_REPO_URL", raising=False)
    html = (
        "<p>See <code>sweeps/main_job/results.json</code> and <code>sweeps/no_such_record/x.json</code>, "
        "<code>sweeps/&lt;study&gt;/</code>, <a href='x'><code>sweeps/main_job/</code></a>.</p>"
        "<pre><span></span><code>graf-report runs=sweeps/main_job\n</code></pre>"
    )
    missing: list[str] = []
    out = record_links.link_records(html, "how-to/install/", ROOT, missing, "how-to/install.md")
    assert '<a href="../../../sweeps/main_job/results.json"><code>sweeps/main_job/results.json</code></a>' in out
    assert missing == ["how-to/install.md: sweeps/no_such_record/x.json"]
    assert out.count("<a ") == 2  # the placeholder, the linked one and the code block are left as they were
    monkeypatch.setenv("GRAF_REPO_URL", "https://example.org/graf")
    out = record_links.link_records(html, "", ROOT, [], "index.md")
    assert 'href="https://example.org/graf/blob/main/sweeps/main_job/results.json"' in out
    assert record_links.target("sweeps/main_job", "", ROOT, "https://example.org/graf", "v1") == (
        "https://example.org/graf/tree/v1/sweeps/main_job"
    )


@pytest.mark.slow  # builds the whole site (about 20 s)
def test_every_cited_record_path_in_the_built_site_is_a_link_that_resolves(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "GRAF_REPO_URL"} | {"NO_MKDOCS_2_WARNING": "1"}
    site = tmp_path / "site"
    p = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-3000:]
    links, bare = 0, []
    for page in site.rglob("*.html"):
        html = page.read_text()
        built_at = ROOT / record_links.SITE_DIR / page.relative_to(site)  # where a clone's build puts the page
        for href in re.findall(r'<a href="([^"]*sweeps/[^"]*)"><code>', html):
            links += 1
            assert (built_at.parent / href).resolve().exists(), f"{page.relative_to(site)}: {href}"
        for m in re.finditer(r"(?<!\">)(?<!<pre>)<code>(sweeps/[^<]*)</code>", html):
            if not record_links.PATTERN.search(m.group(1)):
                bare.append(f"{page.relative_to(site)}: {m.group(1)}")
    assert links > 100 and bare == []
