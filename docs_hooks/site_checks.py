"""How wide a table of the site is, without a browser: so the build can split a generated table that would not fit
the page's content column, and the build test (``tests/test_docs_layout.py``) can fail on a table whose right-hand
columns a reader at 1,400 px would find behind a scroll bar.

A table at its narrowest (its min-content width, which the browser will not go below) is, per column, the widest
of its cells' longest unbreakable pieces plus the cell's padding (a header cell at least ``TH_MIN_PX``), summed
over the columns, plus the table's border.  A piece is a run of text between spaces (the browser also breaks
after a hyphen or a dash); in a table a ``code`` span breaks at the same places (``extra.css`` undoes Material's
``word-break: break-word``, which cut identifiers anywhere).  Widths are those of DejaVu Sans (regular, bold in
headers; DejaVu Sans Mono in code) at the table's 12.8 px: the fonts headless Chromium uses here (Roboto, the
theme's font, comes from Google Fonts, which it does not reach), and wider than Roboto, Helvetica or Arial, so a
table that fits here fits a reader's browser.

The content column at a 1,400 px viewport (Material 9: 1 rem = 20 px below 1,600 px): 1,400 px less each sidebar
shown (12.1 rem; the Results pages hide the table of contents: ``hooks.WIDE_PAGES``) less the content's margins
(1.2 rem beside a sidebar, 0.8 rem otherwise): 868 px with both sidebars, 1,118 px without the table of contents.

Calibration: ``AUDIT=1 bash scripts/site_screenshots.sh`` measures every table of a built site in headless
Chromium at 1,400 px and ``python scripts/site_audit.py`` compares.  On the site with its generated tables left
whole (166 tables, 8 of them behind a scroll bar in Chromium, by 84 to 798 px), the estimated narrowest width
minus Chromium's was from -0.4 to +4.5 px (median +0.4 px, 95% of tables within 2.2 px), and the tables
estimated wider than their column were exactly Chromium's 8; on the site as built (172 tables, the generated
ones split), the same agreement and none behind a scroll bar in either.
"""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

VIEWPORT_PX = 1400
REM_PX = 20.0  # Material: html { font-size: 125% } below 100em
SIDEBAR_PX = 12.1 * REM_PX
FONT_PX = 0.64 * REM_PX  # .md-typeset table:not([class]) { font-size: .64rem }
# extra.css: the cells' padding and the header cells' least width (Material's own, 1.25em and 5rem, would put the
# right-hand columns of the results' tables behind a scroll bar); tests/test_docs_layout.py reads them there too
CELL_PAD_EM = 0.75
TH_MIN_PX = 0.0
TABLE_BORDER_PX = 2 * 0.05 * REM_PX
# code: .85em of DejaVu Sans Mono (0.602 em a character) with 0.294 em of padding on each side of each piece; in a
# table it breaks only where text does (extra.css: word-break normal), so an identifier is never cut in two
MONO_PX = 0.85 * FONT_PX * 0.602
CODE_PAD_PX = 2 * 0.2941176471 * 0.85 * FONT_PX

# DejaVu Sans advance widths (1/1000 em) of the printable ASCII characters, from space to "~": regular, bold
_REGULAR = (
    "318 401 460 838 636 950 780 275 390 390 500 838 318 361 318 337 636 636 636 636 636 636 636 636 636 636 337 "
    "337 838 838 838 531 1000 684 686 698 770 632 575 775 752 295 295 656 557 863 748 787 603 787 695 635 611 732 "
    "684 989 685 611 685 390 337 390 838 500 500 613 635 550 635 615 352 635 634 278 278 579 278 974 634 612 635 "
    "635 411 521 392 634 592 818 592 592 525 636 337 636 838"
)
_BOLD = (
    "348 456 521 838 696 1002 872 306 457 457 523 838 380 415 380 365 696 696 696 696 696 696 696 696 696 696 400 "
    "400 838 838 838 580 1000 774 762 734 830 683 683 821 837 372 372 775 637 995 837 850 733 850 770 720 682 812 "
    "774 1103 771 724 725 457 365 457 838 500 500 675 716 593 716 678 435 716 712 343 343 665 343 1042 712 687 716 "
    "716 493 595 478 712 652 924 645 652 582 712 365 712 838"
)
WIDTHS = {
    bold: dict(zip(map(chr, range(32, 127)), map(int, table.split())))
    for bold, table in ((False, _REGULAR), (True, _BOLD))
}
OTHER_EM = 0.84  # arrows, signs (→ ↑ × ≥ ±) and anything else outside ASCII: DejaVu Sans draws most at 838
# inside a run without spaces, Chromium breaks after a hyphen or a dash, before an em dash, after a slash before a
# character outside ASCII (error/ΔP²; not in v2/v3)
BREAK = re.compile(r"(?<=[A-Za-z0-9]-)|(?<=[–—])|(?=—)|(?<=/)(?=[^\x00-\x7f])")


def text_width(text: str, bold: bool = False, code: bool = False) -> float:
    if code:
        return len(text) * MONO_PX + CODE_PAD_PX
    table = WIDTHS[bold]
    return sum(table.get(c, OTHER_EM * 1000) for c in text) * FONT_PX / 1000


def piece_width(text: str, bold: bool = False) -> float:
    """The widest unbreakable piece of ``text`` (0 for blank text)."""
    return max((text_width(p, bold) for w in text.split() for p in BREAK.split(w)), default=0.0)


def cell_width(runs: list[tuple[str, str]], header: bool = False) -> float:
    """A cell at its narrowest: ``runs`` are (text, style) with style ``""``, ``"b"`` (bold) or ``"code"``; a piece
    that spans runs (``**3**x``) is measured whole."""
    best, cur = 0.0, 0.0
    for text, style in runs:
        bold, code = header or style == "b", style == "code"
        for w in re.split(r"(\s+)", text):
            if not w:
                continue
            if w.isspace():
                best, cur = max(best, cur), 0.0
                continue
            parts = BREAK.split(w)
            for j, p in enumerate(parts):
                cur += text_width(p, bold, code)
                if j < len(parts) - 1:
                    best, cur = max(best, cur), 0.0
    return max(best, cur) + 2 * CELL_PAD_EM * FONT_PX


def table_width(rows: list[list[list[tuple[str, str]]]]) -> float:
    """A table at its narrowest: ``rows`` of cells (each a list of runs), the header row first."""
    n = max(len(r) for r in rows)
    cols = [0.0] * n
    for k, row in enumerate(rows):
        for i, cell in enumerate(row):
            w = cell_width(cell, header=k == 0)
            cols[i] = max(cols[i], w, TH_MIN_PX if k == 0 else 0.0)
    return sum(cols) + TABLE_BORDER_PX


def column_width(toc: bool = True, nav: bool = True) -> float:
    """The content column at 1,400 px, with or without each sidebar."""
    sides = (toc, nav)
    return VIEWPORT_PX - sum(SIDEBAR_PX for s in sides if s) - sum((1.2 if s else 0.8) * REM_PX for s in sides)


# --- markdown tables, as the hooks generate them ---

MD_RUN = re.compile(r"`([^`]*)`|\*\*(.+?)\*\*|\[([^\]]*)\]\([^)]*\)")


def md_cells(line: str) -> list[str]:
    """A markdown table row's cells (``\\|`` is a ``|`` inside a cell)."""
    body = line.strip().removeprefix("|").removesuffix("|")
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", body)]


def md_runs(cell: str) -> list[tuple[str, str]]:
    out, at = [], 0
    for m in MD_RUN.finditer(cell):
        out.append((cell[at : m.start()].replace("*", ""), ""))
        if m.group(1) is not None:
            out.append((m.group(1), "code"))
        else:
            out.append((m.group(2) if m.group(2) is not None else m.group(3), "b" if m.group(2) is not None else ""))
        at = m.end()
    return out + [(cell[at:].replace("*", ""), "")]


def _numeric(cell: str) -> bool:
    return bool(re.fullmatch(r"[-+*(]*[\d.,]+(e[-+]?\d+)?[)%*]*( \(.*\))?|-", cell.strip()))


PREFERRED_PX = 160.0  # a column of text gets up to this much of its one-line width when columns are grouped
GLUED = re.compile(r"^(×|x |slowdown)")  # a ratio's column stays beside the column it is the ratio of


def max_width(runs: list[tuple[str, str]], header: bool = False) -> float:
    """A cell on one line (its max-content width)."""
    one = [(" ".join(t.split()), st) for t, st in runs]
    text = sum(text_width(t, header or st == "b", st == "code") for t, st in one if t)
    return text + 2 * CELL_PAD_EM * FONT_PX


def split_table(lines: list[str], width: float) -> list[list[str]]:
    """A markdown table (its lines) as tables of at most ``width`` px each: unchanged when it fits; otherwise its
    columns in groups that fit, each group after the row labels (the leading columns that are not figures, at
    most three), so each part is read by the same rows.  Columns are grouped at their preferred widths (their
    one-line width, up to ``PREFERRED_PX``, at least their narrowest), so a column of prose is not squeezed to
    its longest word."""
    rows = [md_cells(x) for i, x in enumerate(lines) if i != 1]
    n = len(rows[0])
    cells = [[(md_runs(r[i]) if i < len(r) else [], k == 0) for k, r in enumerate(rows)] for i in range(n)]
    least = [max(cell_width(c, h) for c, h in col) for col in cells]
    if sum(least) + TABLE_BORDER_PX <= width or n < 3:
        return [lines]
    pref = [max(lo, min(PREFERRED_PX, max(max_width(c, h) for c, h in col))) for lo, col in zip(least, cells)]
    keys = 1
    while keys < min(3, n - 2) and not any(_numeric(r[keys]) for r in rows[1:] if keys < len(r)):
        keys += 1
    units: list[list[int]] = []
    for i in range(keys, n):
        if units and GLUED.match(rows[0][i]):
            units[-1].append(i)
        else:
            units.append([i])
    room = width - TABLE_BORDER_PX - sum(pref[:keys])
    groups, used = [[]], 0.0
    for unit in units:
        w = sum(pref[i] for i in unit)
        if groups[-1] and used + w > room:
            groups.append([])
            used = 0.0
        groups[-1].extend(unit)
        used += w
    out = []
    for g in groups:
        idx = list(range(keys)) + g
        esc = [[(r[i] if i < len(r) else "").replace("|", "\\|") for i in idx] for r in rows]
        head = ["| " + " | ".join(esc[0]) + " |", "|" + "---|" * len(idx)]
        out.append(head + ["| " + " | ".join(r) + " |" for r in esc[1:]])
    return out


def fit_tables(markdown: str, width: float) -> str:
    """Every table of ``markdown`` split (:func:`split_table`) to fit ``width`` px; a continued table says so."""
    out, block = [], []

    def flush():
        if block:
            parts = split_table(block, width)
            for k, part in enumerate(parts):
                if k:
                    out.extend(["", f"*The same rows, continued ({k + 1} of {len(parts)}):*", ""])
                out.extend(part)
            block.clear()

    for line in markdown.split("\n"):
        if line.startswith("|"):
            block.append(line)
            continue
        flush()
        out.append(line)
    flush()
    return "\n".join(out)


# --- the built site ---


class _Tables(HTMLParser):
    """A built page's tables (rows of cells, each a list of (text, style) runs) and which sidebars it shows."""

    def __init__(self):
        super().__init__()
        self.tables, self.toc, self.nav = [], True, True
        self._row = self._cell = None
        self._styles: list[str] = []
        self._boxes: list[bool] = []  # the open divs and details: whether each is an admonition

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        cls = a.get("class") or ""
        if tag == "div" and "md-sidebar--secondary" in cls and "hidden" in a:
            self.toc = False
        if tag == "div" and "md-sidebar--primary" in cls and "hidden" in a:
            self.nav = False
        if tag == "table":
            self.tables.append({"rows": [], "boxes": sum(self._boxes)})
        elif tag == "tr" and self.tables:
            self._row = []
            self.tables[-1]["rows"].append(self._row)
        elif tag in ("td", "th") and self._row is not None:
            self._cell = []
            self._row.append(self._cell)
        elif tag in ("code", "strong", "b"):
            self._styles.append("code" if tag == "code" else "b")
        elif tag == "br" and self._cell is not None:
            self._cell.append((" ", ""))
        elif tag in ("div", "details"):
            self._boxes.append("admonition" in cls or tag == "details")

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self._cell = None
        elif tag == "tr":
            self._row = None
        elif tag in ("code", "strong", "b") and self._styles:
            self._styles.pop()
        elif tag in ("div", "details") and self._boxes:
            self._boxes.pop()

    def handle_data(self, data):
        if self._cell is not None:
            style = "code" if "code" in self._styles else ("b" if self._styles else "")
            self._cell.append((data, style))


ADMONITION_PX = 1.45 * REM_PX  # an admonition's padding and left border, less the table's own


def page_tables(html: str) -> list[tuple[str, float, float]]:
    """Each table of a built page: (its header, its narrowest width, the width it has), in px."""
    parser = _Tables()
    parser.feed(html)
    column = column_width(parser.toc, parser.nav)
    out = []
    for t in parser.tables:
        rows = [r for r in t["rows"] if r]
        if not rows:
            continue
        head = " | ".join("".join(x for x, _ in c).strip() for c in rows[0][:4])
        out.append((head, table_width(rows), column - t["boxes"] * ADMONITION_PX))
    return out


def overflowing_tables(site: Path) -> list[str]:
    """Every table of the built ``site`` wider than its page's content column at 1,400 px: page, header, px."""
    out = []
    for f in sorted(site.rglob("*.html")):
        for k, (head, need, have) in enumerate(page_tables(f.read_text())):
            if need > have:
                name = f.relative_to(site).as_posix()
                out.append(f"{name}: table {k} ({head} ...): {need - have:.0f} px behind a scroll bar at 1,400 px")
    return out
