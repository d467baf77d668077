"""Every figure a record's README states is held by its record, and every figure a site page (or the repository's
README) states is held by the records the page names (``docs_hooks/stated_figures.py``); a README's generated block
is the one its record makes: the check on small made-up files first, then on every ``sweeps/*/README.md`` and every
page."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from docs_hooks.stated_figures import (
    named_records,
    not_held,
    pages_problems,
    readme_problems,
    record_numbers,
    supplement,
)

from graf.errors import UserError
from graf.reports.readme import END, START, block, refresh, split_table, with_block
from graf.reports.table import HEADLINE, markers, with_headline

ROOT = Path(__file__).resolve().parents[2]
OWNED_ELSEWHERE = ("claims", "learning_curves")  # READMEs of records other commands write
READMES = sorted(p.parent.name for p in (ROOT / "sweeps").glob("*/README.md") if p.parent.name not in OWNED_ELSEWHERE)


def _record(folder: Path, readme: str, **files) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, obj in files.items():
        (folder / f"{name}.json").write_text(json.dumps(obj))
    (folder / "README.md").write_text(readme)
    return folder


def test_a_held_figure_passes_and_a_wrong_one_is_named(tmp_path):
    rec = {
        "rows": [{"diff": 0.43119, "low": 0.2281, "high": 0.6031, "reach": 0.2031, "ssim": 0.83249}],
        "confidence": 0.95,
    }
    held = _record(tmp_path / "held", "GRaF is ahead by +0.43 dB [+0.23, +0.60], SSIM 0.832; 95% interval.\n", x=rec)
    assert readme_problems(held, None) == []
    wrong = _record(
        tmp_path / "wrong", "# R\n\nNo interval is more than 0.19 dB either side of its difference.\n", x=rec
    )
    problems = readme_problems(wrong, None)
    assert len(problems) == 1 and problems[0].startswith(f"{wrong / 'README.md'}:3: 0.19 ")
    # a sign written is a sign checked; a figure written without one stands for either ("lower by 0.43")
    assert [p.split()[1] for p in not_held("-0.43 and 0.43 and +0.7", record_numbers(held))] == ["-0.43", "+0.7"]


def test_a_figure_of_the_paper_is_held_by_the_paper_text(tmp_path):
    folder = _record(tmp_path / "r", "The paper's L = 2 gives 17.98 dB (57% of ...).\n", x={"psnr": 22.19})
    paper = tmp_path / "supplement.txt"
    paper.write_text("With $L=2$, PSNR decreases to 17.98 dB; 57 of the ...")
    assert readme_problems(folder, paper) == []
    assert [p.split()[1] for p in readme_problems(folder, None)] == ["17.98", "57%"]


def test_code_generated_blocks_comments_and_units_state_no_figure(tmp_path):
    text = "\n".join(
        [
            "Run it:",
            "",
            "    graf-train lr=0.19",
            "",
            "```",
            "PSNR 0.19",
            "```",
            "`model.lr=0.19` <!-- gen: include x 0.19 --> ([link](sweeps/a_0.19.png))",
            START,
            "| 0.19 |",
            END,
            "Training took 0.19 s a step (0.18-0.19 s/step) at 2.4 GHz, 0.19 m apart, on 1.8ghz data.",
            "A figure after them: 0.19 dB.",
        ]
    )
    assert [p.split()[1] for p in not_held(text, record_numbers(_record(tmp_path, "", x={"v": 1.5})), "t")] == ["0.19"]


def test_settings_sizes_and_confidence_levels_state_no_figure(tmp_path):
    held = record_numbers(_record(tmp_path, "", x={"v": 1.5}))
    text = "\n".join(
        [
            "Adam lr 1e-3, tested to 4e-7; `graf-eval` with lr=0.0005; a room 7.2 x 14.9 x 6.2, a 95%",
            "bootstrap interval and a 95% interval; a step took 0.44",  # the unit on the next line
            "s/step, and PSNR rose by 2.2 dB.",
        ]
    )
    assert [p.split()[1] for p in not_held(text, held, "t")] == ["2.2"]


def _site(root: Path, pages: dict[str, str], records: dict[str, dict]) -> Path:
    for name, obj in records.items():
        _record(root / "sweeps" / name, "", x=obj)
    for path, text in {"README.md": "# Project\n", **pages}.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_text(text)
    return root


def test_a_page_figure_is_held_only_by_the_records_the_page_names(tmp_path):
    """A figure held by another record than the page names fails: with every record as the record, most
    two-decimal figures would be held by chance."""
    records = {"bands": {"psnr": 22.31}, "density": {"psnr": 17.44}}
    pages = {
        "docs/held.md": "GRaF: 22.31 dB (`sweeps/bands/`).\n",
        "docs/directive.md": "<!-- gen: study bands -->\n\nGRaF: 22.31 dB.\n",
        "docs/records_link.md": "GRaF: 22.31 dB ([its record](records.md#bands)).\n",
        "docs/elsewhere.md": "GRaF: 22.31 dB (`sweeps/density/`).\n",
        "docs/unnamed.md": "GRaF: 22.31 dB.\n",
        "docs/reproducibility.md": "It took 3.14 h... and scored 99.99.\n",
    }
    root = _site(tmp_path, pages, records)
    assert [p.name for p in named_records(pages["docs/directive.md"], root / "sweeps")] == ["bands"]
    problems = pages_problems(root)
    assert [p.split(":")[0] for p in problems] == ["docs/elsewhere.md", "docs/unnamed.md"]
    assert problems[0].startswith("docs/elsewhere.md:1: 22.31 ") and "names no record" not in problems[0]
    assert "the page names no record" in problems[1]


def test_the_block_replaces_its_old_self_and_keeps_the_text_around_it():
    old = f"# Title\n\nHow it was run.\n\n{START}\nold tables\n{END}\n\nA note after.\n"
    assert (
        with_block(old, f"{START}\nnew\n{END}", "t")
        == f"# Title\n\nHow it was run.\n\n{START}\nnew\n{END}\n\nA note after.\n"
    )
    assert with_block("# Title\n\nProse.\n", "B", "t") == "# Title\n\nProse.\n\nB\n"
    assert with_block("", "B", "bands") == "# bands\n\nB\n"
    with pytest.raises(UserError, match="no end marker"):
        with_block(f"{START}\nno end", "B", "t")


def test_a_wide_table_is_split_with_its_label_columns_in_each_part():
    lines = ["| method | trained on | a | b | c | d | e | f |", "|---|---|---|---|---|---|---|---|"]
    lines += ["| graf | conference_v1 | 1.00 | 2.00 | 3.00 | 4.00 | 5.00 | 6.00 |"]
    parts = split_table(lines, 6)
    assert [p.split("\n")[0] for p in parts] == [
        "| method | trained on | a | b | c |",
        "| method | trained on | d | e | f |",
    ]
    assert parts[1].split("\n")[2] == "| graf | conference_v1 | 4.00 | 5.00 | 6.00 |"


def test_refresh_writes_the_tables_and_intervals_of_a_record(tmp_path):
    report = {"band_matrix": {"graf": {"rows": ["915 MHz"], "cols": ["915 MHz", "3 GHz"], "psnr": [[22.314, 20.5]]}}}
    change = {"diff": -0.13, "low": -0.32, "high": 0.061, "verdict": "level (interval includes 0)"}
    cell = {"trained_on": "c1", "train_band": "915 MHz", "finetune": "-", "L": "10", "eval_scene": "c1"}
    rows = [{**cell, "eval_band": b, "method": "graf", "metric": "psnr", "mean": 22.3, "n_seeds": 1, "n_spectra": 120,
             "seed_spread": 0.0, "vs_knn": {"diff": d, "low": d - 0.1, "high": d + r, "verdict": "ahead"}}
            for b, d, r in (("915 MHz", 0.98, 0.33), ("3 GHz", 0.2, 0.25))]  # fmt: skip
    transfer = {**cell, "eval_band": "3 GHz", "method": "graf", "metric": "psnr", **change}
    folder = _record(tmp_path / "bands", "# bands\n\nHow it was run.\n", report=report, rows={"rows": []})
    (folder / "intervals.json").write_text(json.dumps({"rows": rows, "L_changes": [], "band_transfers": [transfer]}))
    text = refresh(folder).read_text()
    assert text.startswith("# bands\n\nHow it was run.\n\n" + START) and text.rstrip().endswith(END)
    assert "| 915 MHz | 22.31 | 20.50 |" in text  # the band matrix (published.study_tables)
    assert "| graf | KNN | PSNR | 2 ahead | +0.20 to +0.98 | 0.33 |" in text  # 0.33: the widest reach
    assert "| 3 GHz | graf | 22.30 | +0.20 [+0.10, +0.45] ahead |" in text  # the test band varies alone
    assert "| graf | 915 MHz | 3 GHz | -0.13 | [-0.32, +0.06] | level |" in text
    assert refresh(folder).read_text() == text  # a second run changes nothing
    assert readme_problems(folder, None) == []
    (folder / "report.json").write_text("{")
    with pytest.raises(UserError, match=r"report\.json: not valid JSON"):
        block(folder)


@pytest.mark.parametrize("name", READMES)
def test_a_record_readme_states_only_figures_its_record_holds(name):
    paper = supplement(ROOT)
    if paper is None:
        pytest.skip("the paper's supplement (../shared/seed/graf_supplementary.txt) is absent: its figures are unread")
    assert readme_problems(ROOT / "sweeps" / name, paper) == []


@pytest.mark.parametrize("name", [n for n in READMES if (ROOT / "sweeps" / n / "report.json").is_file()])
def test_a_study_readme_shows_the_block_its_record_makes(name):
    """The generated block is current (``python scripts/record_readmes.py`` rewrites it)."""
    folder = ROOT / "sweeps" / name
    text = (folder / "README.md").read_text()
    assert START in text and with_block(text, block(folder), name) == text


def test_the_main_job_readme_shows_the_table_its_record_makes():
    """``sweeps/main_job/README.md``'s table is the headline of its ``results.json`` (scripts/record_readmes.py)."""
    text = (ROOT / "sweeps" / "main_job" / "README.md").read_text()
    assert markers(HEADLINE)[0] in text
    assert with_headline(text, json.loads((ROOT / HEADLINE).read_text())) == text


def test_graf_report_writes_the_readme_block_and_refreshes_it_alone(tmp_path):
    """graf-report writes the block into the study folder's README (the text around it kept); ``readme_only=true``
    rewrites it from the folder's own files, reading no job."""
    from hydra import compose, initialize_config_dir

    from graf.app.config import CONF_DIR
    from graf.reports.study import make_report, report
    from tests.reports.test_report import GHZ24, REFERENCE, _result

    knn = {"a_v1": 15.0, "b_v1": 13.0}
    _result(tmp_path / "j0", "graf", ["a_v1"], [("a_v1", 20.0, GHZ24), ("b_v1", 12.0, GHZ24)], knn=knn)
    _result(tmp_path / "j1", "graf", ["b_v1"], [("a_v1", 11.0, GHZ24), ("b_v1", 19.0, GHZ24)], knn=knn)
    out = tmp_path / "out"
    _record(out, "# The study\n\nHow it was run.\n")
    make_report(tmp_path, out, REFERENCE)
    text = (out / "README.md").read_text()
    assert text.startswith("# The study\n\nHow it was run.\n\n" + START)
    assert "| graf | b_v1 | 11.00 | 19.00 |" in text and readme_problems(out, None) == []
    (out / "README.md").write_text(text.replace("| graf | b_v1 | 11.00 | 19.00 |", "| graf | b_v1 | 1.00 | 9.00 |"))
    for job in ("j0", "j1"):
        (tmp_path / job / "results.json").unlink()  # the light path reads no job
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("report", overrides=[f"runs={out}", f"paths.output_dir={tmp_path}", "readme_only=true"])
    report(cfg)
    assert (out / "README.md").read_text() == text


def test_every_site_page_states_only_figures_its_records_hold():
    """``docs/**/*.md`` (the Reproducibility log aside) and README.md: each figure is held by the records the page
    names or by the paper's text (graf.reports.readme.pages_problems)."""
    if supplement(ROOT) is None:
        pytest.skip("the paper's supplement (../shared/seed/graf_supplementary.txt) is absent: its figures are unread")
    assert pages_problems(ROOT) == []
