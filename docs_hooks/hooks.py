"""MkDocs hooks: the pages that describe the code and the records are generated at build time from the tree
(never copied by hand), and the figures of ``sweeps/`` are published beside the pages.

Generated pages (:mod:`tree_pages`): one API reference page per room of the package (``api/<room>.md``, every
public module as a ``::: graf.x.y`` block) and their index (``api/index.md``); the navigation's "API reference"
entry is replaced by them.

A page asks for a generated block with a directive on a line of its own:

- ``<!-- gen: study NAME -->``: the tables of study ``sweeps/NAME`` (its ``report.json`` and ``rows.json``,
  written by graf-report), by :func:`graf.reports.published.study_tables` (as ``scripts/study_tables.py``);
- ``<!-- gen: search NAME -->``: the trials of search ``sweeps/NAME`` (``trials.csv``) and the chosen
  configuration's test beside its baselines (``best/best.json``, ``best/results.json``);
- ``<!-- gen: include PATH -->``: a markdown table a command wrote (``sweeps/learning_curves/curves.md``,
  ``sweeps/compare_rfid_s23/table.md``, ...), included as it is;
- ``<!-- gen: choose PATH -->``: GRaF's modes ranked on validation from a ``curves.csv``
  (:func:`graf.reports.choices.choose`, as ``scripts/choose_graf.py``);
- ``<!-- gen: choosing sweeps -->``: each preset's cost and quality from the records of the runs that trained it
  (:mod:`choosing`);
- ``<!-- gen: distance sweeps/<record> -->``: the neighbour-distance study's advice, figure and table, or how far its
  run has got (:mod:`distance`);
- ``<!-- gen: curve_facts REGIME -->``: a learning-curve regime's facts (its KNN line; per method the best and last
  point, the last slope, the first step past KNN) from ``sweeps/learning_curves/`` (:mod:`curve_facts`);
- ``<!-- gen: code PATH -->``: a source file of the repository as a code block (the worked examples' plugin);
- ``<!-- gen: page PATH -->``: a markdown file of the repository (``CONTRIBUTING.md``) as the page's text;
- ``<!-- gen: layout src -->``: the map of the package (floors, rooms, modules, commands, scripts);
- ``<!-- gen: headline PATH -->``: the main job's table from its record (``sweeps/main_job/results.json``), the
  same table ``scripts/headline.py`` writes into the README;
- ``<!-- gen: records sweeps -->``: one entry per folder of ``sweeps/`` with its figures (:mod:`records`), the
  Records page.
- ``<!-- gen: config NAME -->``, ``<!-- gen: group NAME -->``, ``<!-- gen: interp PATHS -->``: a command's or a config
  file's settings, a config group's options, the interpolation study's table (:mod:`reference`, the reference pages).

A generated table wider than its page's content column at 1,400 px is split into tables of the same rows, each
with the row labels and as many columns as fit (:func:`site_checks.fit_tables`), so no column of figures sits
behind a scroll bar.  The Results pages (the navigation's ``Results`` section) hide the table of contents, which
gives their tables 250 px more.

A directive whose record is missing fails the build (``mkdocs build --strict`` in CI), so a page never shows a
table its records do not hold.  Figures: every ``*.png`` of ``sweeps/`` (at any depth, but in checkpoint, trial
and model folders: :func:`records.figures`) is published at
``sweeps/...``, so a page links ``![](sweeps/NAME/figure.png)`` (from a page in ``docs/``).

This folder is outside ``docs/``, so the hooks are not published with the site; MkDocs loads this file and puts
its folder on ``sys.path`` while it does, which is how ``tree_pages``, ``records``, ``site_checks`` and
``curve_facts`` are imported.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import choosing
import curve_facts
import distance
import page_words
import record_links
import reference
import site_checks
import tree_pages
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

import records
from graf.errors import UserError
from graf.metrics.names import curve_metrics
from graf.reports import choices as curve_choices
from graf.reports import published
from graf.reports import table as headline_table

ROOT = Path(__file__).resolve().parents[1]
SWEEPS = ROOT / "sweeps"
API_NAV = "API reference"
DIRECTIVE = re.compile(r"^<!-- gen: (\w+) (\S+(?: \S+)*) -->$", re.M)  # a generator of GENERATORS and its argument
RESULTS_NAV = "Results"  # the navigation's section whose pages hide the table of contents (WIDE_PAGES)
WIDE_PAGES: set[str] = set()  # filled by on_config
NAV_TITLES: dict[str, str] = {}
PAGE_PROBLEMS: list[str] = []  # what page_words found on the pages of this build (on_post_build fails on any)


def _record(path: Path) -> Path:
    if not path.is_file():
        raise PluginError(f"docs: {path.relative_to(ROOT)} is missing: the page asks for a table of it")
    return path


def study(name: str) -> str:
    folder = SWEEPS / name
    report = json.loads(_record(folder / "report.json").read_text())
    rows = json.loads(_record(folder / "rows.json").read_text())["rows"]
    parts = published.study_tables(report, rows)
    if not parts:
        raise PluginError(f"docs: {folder.relative_to(ROOT)}/report.json holds no table this site knows")
    return "\n\n".join(parts) + f"\n\n*Generated from `sweeps/{name}/report.json` and `rows.json`.*"


def _f(v, spec: str = ".3f") -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return "-"
    return "-" if math.isnan(x) else format(x, spec)


def search(name: str) -> str:
    folder = SWEEPS / name
    with open(_record(folder / "trials.csv"), newline="") as fh:
        trials = list(csv.DictReader(fh))
    best = json.loads(_record(folder / "best" / "best.json").read_text())
    params = [k for k in trials[0] if k.startswith("param ")]
    values = [k for k in trials[0] if k.startswith("value ")]
    body = []
    for t in trials:
        notes = []
        if t.get("interrupted") == "True":
            notes.append("pre-empted")
        if t.get("requeued_from"):
            notes.append(f"trial {t['requeued_from']} re-queued")
        if t.get("duplicate_of"):
            notes.append(f"duplicate of {t['duplicate_of']}")
        if t.get("pareto") == "True":
            notes.append("Pareto front")
        if str(t["number"]) == str(best["trial"]):
            notes.append("**chosen**")
        inter = t.get("last_intermediate_value")
        body.append(
            [
                t["number"],
                *[_param(t[p]) for p in params],
                t["state"],
                *[_f(t[v], ".4g") for v in values],
                f"{_f(inter)} ({t.get('last_intermediate_step') or '-'})" if inter else "-",
                _f(t.get("wall_s"), ".0f"),
                ", ".join(notes),
            ]
        )
    header = ["trial", *[p[len("param ") :] for p in params], "state", *[v[len("value ") :] for v in values]]
    header += ["last val PSNR in training (step)", "wall s", "note"]
    out = [published.md(header, body)]
    res = json.loads(_record(folder / "best" / "results.json").read_text())
    evals = res.get("evaluations") or [{"eval_scene": res["eval_scene"], "metrics": res["metrics"],
                                        "baselines": res.get("baselines") or {}}]  # fmt: skip
    rows = []
    for e in evals:
        rows.append([e["eval_scene"], res["method"], *_figures(e["metrics"])])
        for b, r in sorted((e.get("baselines") or {}).items()):
            rows.append([e["eval_scene"], b, *_figures(r["metrics"])])
    methods = [res["method"], *sorted({b for e in evals for b in (e.get("baselines") or {})})]
    for m in methods:
        ms = [e["metrics"] if m == res["method"] else e["baselines"][m]["metrics"] for e in evals]
        mean = {k: sum(x[k] for x in ms) / len(ms) for k in ms[0] if all(x.get(k) is not None for x in ms)}
        rows.append([f"**mean of {len(ms)}**", m, *_figures(mean)])
    chosen = " ".join(f"`{k}={_param(str(v))}`" for k, v in best["params"].items())
    out.append(
        f"Chosen on validation: trial {best['trial']}, {chosen}; tested once (`best/`):\n\n"
        + published.md(["test scene", "method", *(x.label for x in curve_metrics()), "reliance dB", "val PSNR"], rows)
    )
    return "\n\n".join(out) + f"\n\n*Generated from `sweeps/{name}/trials.csv` and `best/`.*"


def _param(v: str) -> str:
    """A sampled parameter as the trial table shows it: a long float (a log-uniform learning rate) to 3 digits."""
    try:
        x = float(v)
    except ValueError:
        return v
    return format(x, ".3g") if "." in v and len(v) > 8 else v


def _figures(m: dict) -> list[str]:
    """A search's tested figures: each metric the summaries show (the registry's ``on_curves``), the reliance, and
    validation PSNR."""
    own = [_f(m.get(f"test/{x.name}"), x.fmt.strip("{}:")) for x in curve_metrics()]
    return [*own, _f(m.get("test/reliance_db"), ".2f"), _f(m.get("val/psnr"), ".2f")]


def include(path: str) -> str:
    return _record(ROOT / path).read_text().strip() + f"\n\n*Generated from `{path}`.*"


def code(path: str) -> str:
    """A source file of the repository as a fenced block (``tests/plugins/toy_plugin.py``: the worked examples)."""
    lang = {".py": "python", ".yaml": "yaml", ".sh": "bash"}.get(Path(path).suffix, "")
    return f"```{lang}\n{_record(ROOT / path).read_text().rstrip()}\n```\n\n*The file `{path}`, as the tests run it.*"


def leads_knn(regime: str) -> str:
    """The main job's rule on a regime's points (:func:`graf.reports.choices.leading_knn`): each point, whether it
    leads the regime's KNN line in all three validation figures, and the choice."""
    curves = SWEEPS / "learning_curves"
    with open(_record(curves / "curves.csv"), newline="") as fh:
        rows = list(csv.DictReader(fh))
    knn = json.loads(_record(curves / "results.json").read_text()).get("knn", {}).get(regime)
    if knn is None:
        raise PluginError(f"docs: sweeps/learning_curves/results.json has no KNN line of regime {regime}")
    chosen, table = curve_choices.leading_knn(rows, knn, regime)
    body = [[f"`{t['mode']}`", t["step"], _f(t["val_psnr"], ".2f"), _f(t["val_ssim"]), _f(t["val_lpips"]),
             "yes" if t["leads"] else "no"] for t in table]  # fmt: skip
    body.append(["KNN (line)", "-", _f(knn["val/psnr"], ".2f"), _f(knn["val/ssim"]), _f(knn["val/lpips"]), "-"])
    said = f"chosen: `{chosen['mode']}` at {chosen['step']} steps" if chosen else "no point leads KNN in all three"
    head = ["mode", "steps", "val PSNR", "val SSIM", "val LPIPS", "leads KNN in all three"]
    return f"**{regime}**: {said}\n\n" + published.md(head, body)


def choose(path: str) -> str:
    """GRaF's neighbor-feature mode ranked on validation (:func:`graf.reports.choices.choose`), per regime and
    over all."""
    with open(_record(ROOT / path), newline="") as fh:
        rows = list(csv.DictReader(fh))
    modes = ["pooled", "ray", "ray_knn", "ray_weights"]
    out = []
    try:
        choices, waiting, beside = curve_choices.choose_per_regime(
            rows, modes, curve_choices.continued_regimes(), curve_choices.own_run_regimes()
        )
    except UserError as e:
        raise PluginError(f"docs: {path}: {e}") from e
    for regime, chosen, table in choices:
        body = [
            [t["regime"], t["step"], f"**{t['mode']}**" if t["mode"] == chosen else t["mode"], _f(t["val_psnr"], ".2f"),
             _f(t["val_ssim"]), _f(t["val_lpips"]), _f(t["reliance"], ".2f"), _f(t["mean_rank"], ".2f")]
            for t in table
        ]  # fmt: skip
        head = ["regime", "step", "mode", "val PSNR", "val SSIM", "val LPIPS", "val reliance dB", "mean rank"]
        out.append(f"**{regime or 'all regimes together'}**: chosen `{chosen}`\n\n" + published.md(head, body))
    for regime, missing in waiting.items():
        out.append(f"**{regime}**: in progress, no choice yet (no point of {', '.join(f'`{m}`' for m in missing)})")
    for regime, parent, chosen, table in beside:
        body = [
            [t["regime"], t["step"], f"`{t['mode']}`", t["point"], _f(t["val_psnr"], ".2f"), _f(t["val_ssim"]),
             _f(t["val_lpips"]), curve_choices.ahead_label(t)]
            for t in table
        ]  # fmt: skip
        ahead = sorted({t["mode"] for t in table if t["ahead"]})
        verdict = (
            f"ahead of `{chosen}` in some figure: {', '.join(f'`{m}`' for m in ahead)}"
            if ahead
            else f"no point of a continued curve is ahead of `{chosen}` in any figure"
        )
        head = ["regime", "step", "mode", "point", "val PSNR", "val SSIM", "val LPIPS", "ahead of the choice in"]
        out.append(
            f"**{regime}** continues `{parent}` (no choice of its own; the rule ranks at the largest step every mode "
            f"reached): beside `{parent}`'s choice, `{chosen}`, each continued curve's best and last points; "
            f"{verdict}.\n\n" + published.md(head, body)
        )
    return "\n\n".join(out) + f"\n\n*Generated from `{path}` by `scripts/choose_graf.py`.*"


def headline(path: str) -> str:
    """The main job's headline table (:func:`graf.reports.table.headline`), the README's too."""
    return headline_table.headline(json.loads(_record(ROOT / path).read_text()), path)


def page_file(path: str) -> str:
    """A markdown file of the repository (``CONTRIBUTING.md``) as a page, its ``docs/`` links made page-relative."""
    return _record(ROOT / path).read_text().replace("](docs/", "](")


def layout(src: str) -> str:
    """The map of the package in ``src`` (the directive names the tree for the reader; there is only that one)."""
    if src != "src":
        raise PluginError(f"docs: <!-- gen: layout {src} -->: the layout is made from src")
    note = "*Generated from `src/`, `pyproject.toml`, `scripts/` and `tests/test_import_graph.py`.*"
    return tree(tree_pages.layout, ROOT) + "\n\n" + note


def tree(make, *args):
    """``make(*args)`` of :mod:`tree_pages`, its refusal as the build's error."""
    try:
        return make(*args)
    except tree_pages.TreeError as e:
        raise PluginError(f"docs: {e}") from e


def on_config(config):
    """The navigation's "API reference" entry becomes the generated pages, the index first; the pages of its
    Results section are noted (:data:`WIDE_PAGES`), and every page's title (the Records page's links)."""
    WIDE_PAGES.clear()
    PAGE_PROBLEMS.clear()
    for item in config["nav"]:
        if isinstance(item, dict) and isinstance(item.get(RESULTS_NAV), list):
            WIDE_PAGES.update(records.nav_titles(item[RESULTS_NAV]))
    NAV_TITLES.clear()
    NAV_TITLES.update(records.nav_titles(config["nav"]))
    pages = [{title: path} for path, (title, _) in tree(tree_pages.api_pages, ROOT).items()]

    def replace(items: list) -> bool:  # the entry at any depth of the navigation (it sits under Reference)
        for i, item in enumerate(items):
            if isinstance(item, dict) and API_NAV in item:
                items[i] = {API_NAV: pages}
                return True
            if isinstance(item, dict) and any(isinstance(v, list) and replace(v) for v in item.values()):
                return True
        return False

    if replace(config["nav"]):
        return config
    raise PluginError(f"docs: mkdocs.yml's nav has no {API_NAV!r} entry for the generated API pages")


# The search ranks the pages a reader wants above the API reference, whose many short entries (one per function)
# otherwise come first for "neighbor" or "KNN": Material's per-page search boost (page.meta search.boost).
# The task pages come first for the words of their task ("install", "resume", "GPU", "own data"), above the
# pages that mention them in passing (the command reference, the reproducibility log).
SEARCH_BOOST = {"neighbors.md": 4.0, "methods/": 3.0, "how-to/install.md": 4.0, "how-to/resume.md": 4.0,
                "how-to/own-data.md": 4.0, "scaling-out.md": 4.0, "data.md": 2.0, "api/": 0.25}  # fmt: skip


def search_boost(src_uri: str) -> float | None:
    """The search boost of the page at ``src_uri`` (None: Material's default, 1)."""
    for prefix, boost in SEARCH_BOOST.items():
        if src_uri == prefix or (prefix.endswith("/") and src_uri.startswith(prefix)):
            return boost
    return None


def records_page(folder: str) -> str:
    """The Records page: an entry per folder of ``sweeps/`` (:mod:`records`)."""
    if folder != "sweeps":
        raise PluginError(f"docs: <!-- gen: records {folder} -->: the records are those of sweeps")
    return records.page(SWEEPS, ROOT, NAV_TITLES)


GENERATORS = {"study": study, "search": search, "include": include, "code": code, "page": page_file,
              "choose": choose, "leads_knn": leads_knn, "curve_facts": curve_facts.block, "layout": layout,
              "headline": headline, "records": records_page, "choosing": choosing.table,
              "distance": distance.block}  # fmt: skip  # <!-- gen: NAME ARG --> on a line of its own


def on_page_markdown(markdown: str, page, config, files) -> str:
    boost = search_boost(page.file.src_uri)
    if boost is not None:
        page.meta.setdefault("search", {}).setdefault("boost", boost)
    hide = page.meta.setdefault("hide", [])
    if page.file.src_uri in WIDE_PAGES and "toc" not in hide:
        hide.append("toc")
    width = site_checks.column_width(toc="toc" not in hide, nav="navigation" not in hide)

    def expand(m: re.Match) -> str:
        kind, arg = m.group(1), m.group(2)
        if kind not in GENERATORS:
            return m.group(0)  # left as it is: reported below
        text = GENERATORS[kind](arg)
        return text if kind == "code" else site_checks.fit_tables(text, width)

    markdown = reference.expand(markdown, page.file.src_uri, fit=lambda text: site_checks.fit_tables(text, width))
    markdown = DIRECTIVE.sub(expand, markdown)
    PAGE_PROBLEMS.extend(
        f"{page.file.src_uri}: {line.strip()} names no generator this site knows (docs_hooks/hooks.py GENERATORS)"
        for line in markdown.splitlines()
        if line.startswith("<!-- gen:")
    )
    problems = page_words.development_words(markdown, page.file.src_uri)
    problems += page_words.shell_problems(markdown, page.file.src_uri)
    PAGE_PROBLEMS.extend(problems)
    return markdown


SPHINX_ROLE = re.compile(r":(?:mod|func|class|meth|data|attr|exc|obj):(?=<code>)")


def on_page_content(html: str, page, config, files) -> str:
    """Docstrings written with Sphinx roles (``:func:`name```) render as the code span alone: mkdocstrings does
    not read the roles, which would otherwise print literally on the API pages.  Every record path a page cites
    becomes a link to it (:mod:`record_links`)."""
    missing: list[str] = []
    html = record_links.link_records(SPHINX_ROLE.sub("", html), page.url, ROOT, missing, page.file.src_uri)
    PAGE_PROBLEMS.extend(f"{m}: a record path that is not in the repository" for m in missing)
    return html


def on_files(files, config):
    site = config["site_dir"]
    for png in records.figures(SWEEPS):
        uri = png.relative_to(ROOT).as_posix()
        files.append(File(uri, src_dir=str(ROOT), dest_dir=site, use_directory_urls=config["use_directory_urls"]))
    for path, (_, text) in tree(tree_pages.api_pages, ROOT).items():
        files.append(File.generated(config, path, content=text))
    return files


def on_post_build(config):
    """The build fails on a development-log word on a user page or a shell block bash cannot parse
    (:mod:`page_words`), every one listed."""
    if PAGE_PROBLEMS:
        raise PluginError("docs: pages a reader cannot act on as they are:\n  " + "\n  ".join(PAGE_PROBLEMS))
