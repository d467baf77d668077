"""Records one click away: every record path a page cites (inline code ``sweeps/...``) becomes a link to it.

Where the site and the repository are published (``GRAF_REPO_URL``, the ``repo_url`` of ``mkdocs.yml``), the link
opens the file in the repository (``<repo_url>/blob/<GRAF_REPO_REF or main>/sweeps/...``).  Unset, it is a link
relative to the page into the clone the site was built in, which resolves when the built site (``site/`` at the
repository's root, MkDocs' default) is served from the repository's root, e.g. ``python -m http.server`` there and
``http://localhost:8000/site/``.  Applied to the rendered HTML (``hooks.on_page_content``), so code blocks and the
tables' widths are left as they were.  A cited path that is not in the repository is reported (:data:`MISSING`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

SITE_DIR = "site"  # where `mkdocs build` writes the site in a clone: the relative links count from there
# an inline code span holding a path under sweeps/ (group 2), unless it is already a link's text (group 1)
CITED = re.compile(r"(<a\b[^>]*>\s*<code>sweeps/[^<]*</code>)|(?<!<pre>)<code>(sweeps/[^<\s]*?)</code>")
PATTERN = re.compile(r"[<>{}*?]|&lt;|&gt;")  # a path with a placeholder or a glob names no one file


def target(path: str, page_url: str, root: Path, repo_url: str | None = None, ref: str | None = None) -> str:
    """The address of the repository's file or folder ``path`` from the page at ``page_url`` (MkDocs' page URL,
    ``claims/`` or ``""``)."""
    if repo_url:
        return f"{repo_url.rstrip('/')}/{'tree' if (root / path).is_dir() else 'blob'}/{ref or 'main'}/{path}"
    depth = len([p for p in page_url.split("/") if p])
    return "../" * (depth + 1) + path  # up from the page's folder to the site's root, then out of site/


def link_records(html: str, page_url: str, root: Path, missing: list[str], name: str = "") -> str:
    """``html`` with every cited record path a link (:func:`target`); paths not in the repository are added to
    ``missing`` (``page: path``) and left as they are."""
    repo_url, ref = os.environ.get("GRAF_REPO_URL") or None, os.environ.get("GRAF_REPO_REF") or None

    def one(m: re.Match) -> str:
        if m.group(1):
            return m.group(0)
        path = m.group(2).split("#", 1)[0].rstrip(".,;:)")
        if PATTERN.search(path):
            return m.group(0)
        if not (root / path).exists():
            missing.append(f"{name}: {path}")
            return m.group(0)
        return f'<a href="{target(path, page_url, root, repo_url, ref)}">{m.group(0)}</a>'

    return CITED.sub(one, html)
