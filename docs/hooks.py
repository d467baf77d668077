"""MkDocs hooks: the study, search and curve tables of the site are generated at build time from the records in
``sweeps/`` (never copied by hand), and the figures there are published beside the pages.

A page asks for a generated block with a directive on a line of its own:

- ``<!-- gen: study NAME -->``: the tables of study ``sweeps/NAME`` (its ``report.json`` and ``rows.json``,
  written by graf-report), by ``scripts/study_tables.py``;
- ``<!-- gen: search NAME -->``: the trials of search ``sweeps/NAME`` (``trials.csv``) and the chosen
  configuration's test beside its baselines (``best/best.json``, ``best/results.json``);
- ``<!-- gen: include PATH -->``: a markdown table a command wrote (``sweeps/learning_curves/curves.md``,
  ``sweeps/compare_rfid_s23/table.md``, ...), included as it is;
- ``<!-- gen: choose PATH -->``: GRaF's modes ranked on validation from a ``curves.csv`` (``scripts/choose_graf.py``);
- ``<!-- gen: page PATH -->``: a markdown file of the repository (``CONTRIBUTING.md``) as the page's text.

A directive whose record is missing fails the build (``mkdocs build --strict`` in CI), so a page never shows a
table its records do not hold.  Figures: every ``*.png`` of ``sweeps/`` (three folders deep) is published at
``sweeps/...``, so a page links ``![](sweeps/NAME/figure.png)`` (from a page in ``docs/``).
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import re
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
SWEEPS = ROOT / "sweeps"
DIRECTIVE = re.compile(r"^<!-- gen: (study|search|include|page|choose) (\S+) -->$", re.M)


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _study_tables():
    return _script("study_tables")


def _record(path: Path) -> Path:
    if not path.is_file():
        raise PluginError(f"docs: {path.relative_to(ROOT)} is missing: the page asks for a table of it")
    return path


def study(name: str) -> str:
    st = _study_tables()
    folder = SWEEPS / name
    report = json.loads(_record(folder / "report.json").read_text())
    rows = json.loads(_record(folder / "rows.json").read_text())["rows"]
    parts = []
    if "matrix" in report:
        parts.append(st.matrix(report, rows))
    if "vs_L" in report:
        parts.append(st.vs_l(report, rows))
        parts.append(st.per_pair(rows))
    if "vs_fraction" in report:
        parts.append(st.unseen(rows))
    if "band_matrix" in report:
        parts.append(st.bands(report))
    if not parts:
        raise PluginError(f"docs: {folder.relative_to(ROOT)}/report.json holds no table this site knows")
    return "\n\n".join(parts) + f"\n\n*Generated from `sweeps/{name}/report.json` and `rows.json`.*"


def _f(v, spec: str = ".3f") -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return "-"
    return "-" if math.isnan(x) else format(x, spec)


def _md(header: list[str], body: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in body])


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
    out = [_md(header, body)]
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
        + _md(["test scene", "method", "PSNR", "SSIM", "LPIPS", "reliance dB", "val PSNR"], rows)
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
    return [
        _f(m.get("test/psnr"), ".2f"),
        _f(m.get("test/ssim")),
        _f(m.get("test/lpips")),
        _f(m.get("test/reliance_db"), ".2f"),
        _f(m.get("val/psnr"), ".2f"),
    ]


def include(path: str) -> str:
    return _record(ROOT / path).read_text().strip() + f"\n\n*Generated from `{path}`.*"


def choose(path: str) -> str:
    """GRaF's neighbor-feature mode ranked on validation by ``scripts/choose_graf.py``, per regime and over all."""
    cg = _script("choose_graf")
    with open(_record(ROOT / path), newline="") as fh:
        rows = list(csv.DictReader(fh))
    modes = ["pooled", "ray", "ray_knn", "ray_weights"]
    out = []
    for regime in sorted({r["regime"] for r in rows if r["method"] in modes}) + [None]:
        chosen, table = cg.choose([r for r in rows if regime is None or r["regime"] == regime], modes)
        body = [
            [t["regime"], t["step"], f"**{t['mode']}**" if t["mode"] == chosen else t["mode"], _f(t["val_psnr"], ".2f"),
             _f(t["val_ssim"]), _f(t["val_lpips"]), _f(t["reliance"], ".2f"), _f(t["mean_rank"], ".2f")]
            for t in table
        ]  # fmt: skip
        head = ["regime", "step", "mode", "val PSNR", "val SSIM", "val LPIPS", "val reliance dB", "mean rank"]
        out.append(f"**{regime or 'all regimes together'}**: chosen `{chosen}`\n\n" + _md(head, body))
    return "\n\n".join(out) + f"\n\n*Generated from `{path}` by `scripts/choose_graf.py`.*"


def page_file(path: str) -> str:
    """A markdown file of the repository (``CONTRIBUTING.md``) as a page, its ``docs/`` links made page-relative."""
    return _record(ROOT / path).read_text().replace("](docs/", "](")


def on_page_markdown(markdown: str, page, config, files) -> str:
    def expand(m: re.Match) -> str:
        kind, arg = m.group(1), m.group(2)
        return {"study": study, "search": search, "include": include, "page": page_file, "choose": choose}[kind](arg)

    return DIRECTIVE.sub(expand, markdown)


def on_files(files, config):
    site = config["site_dir"]
    for png in sorted(SWEEPS.glob("*/*.png")) + sorted(SWEEPS.glob("*/*/*.png")):
        if png.parent.name.startswith(("trial_", "model=")):
            continue
        uri = png.relative_to(ROOT).as_posix()
        files.append(File(uri, src_dir=str(ROOT), dest_dir=site, use_directory_urls=config["use_directory_urls"]))
    return files
