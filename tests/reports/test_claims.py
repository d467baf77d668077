"""The claims ledger is built from records alone: synthetic study jobs (results.json and per-spectrum records of
GRaF and KNN-DL over three seeds, KNN beside them) go through graf-report's intervals, and the ledger of the real
claims config, rebuilt from that folder, gives each claim the verdict its intervals call for."""

from __future__ import annotations

import csv
import json
import re
from collections import Counter

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from graf.app.config import CONF_DIR
from graf.reports.claims import ledger, write_ledger
from graf.reports.claims.findings import VERDICTS as FINDING_VERDICTS
from graf.reports.intervals import write_intervals
from graf.run.per_spectrum import write_per_spectrum

SCENES = {"conference_v1": ["conference_v2", "conference_v3"], "office_v1": ["office_v2", "office_v3"]}


def _job(folder, method, seed, trained_on, values, L=None, sim_num_tx=None):
    """A study job: results.json and per_spectrum.csv.gz with ``values`` {(eval_scene, method): {id: psnr}}."""
    folder.mkdir(parents=True)
    rows = [
        {"eval_scene": s, "method": m, "id": i, "mse": 10 ** (-v / 10), "psnr": v, "ssim": 0.5, "lpips": 0.3}
        for (s, m), per in values.items()
        for i, v in per.items()
    ]
    write_per_spectrum(folder / "per_spectrum.csv.gz", rows)
    result = {
        "method": method,
        "scene": trained_on,
        "train_scenes": [trained_on],
        "metrics": {"test/psnr": 0.0},
        "config": {"seed": seed, "sim_num_tx": sim_num_tx, "neighbors": {"L": L}},
        "per_spectrum": "per_spectrum.csv.gz",
        "evaluations": [{"eval_scene": s, "metrics": {}, "baselines": {}} for s in {k[0] for k in values}],
    }
    (folder / "results.json").write_text(json.dumps(result))


def _study(root, shift_graf, shift_dl, sim_num_tx=None, L_values=(None,), scenes=SCENES):
    rng = np.random.default_rng(0)
    ids = list(range(100, 220))
    for trained, tests in scenes.items():
        base = {s: rng.normal(15.0, 3.0, len(ids)) for s in tests}
        for L in L_values:
            lift = 0.0 if L in (None, 4, 10) else -1.5  # L = 2 worse by 1.5 dB
            for seed in (0, 1, 2):
                for method, shift in ((GRAF, shift_graf), ("knn-dl", shift_dl)):
                    values = {}
                    for s in tests:
                        noise = rng.normal(0.0, 0.3, len(ids))
                        values[(s, method)] = dict(zip(ids, base[s] + shift + lift + noise))
                        values[(s, "knn")] = dict(zip(ids, base[s]))
                    name = f"model={method},scene={trained},seed={seed},L={L}"
                    _job(root / name, method, seed, trained, values, L=L, sim_num_tx=sim_num_tx)


def _claims():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("claims")
    return OmegaConf.to_container(cfg.claims, resolve=True)


GRAF = _claims()[0]["method"]  # the studies' GRaF method name the ledger reads (conf/claims.yaml method)


def test_the_ledger_is_rebuilt_from_records_with_the_verdicts_their_intervals_give(tmp_path):
    runs = tmp_path / "multirun" / "cross_scene_matrix"
    _study(runs, shift_graf=0.6, shift_dl=0.1)
    out = _matrix_record(tmp_path)
    out.mkdir(parents=True)
    rows = write_intervals(runs, out)
    cells = {(r["eval_scene"], r["method"]) for r in rows if r["metric"] == "psnr"}
    assert ("conference_v2", GRAF) in cells and all(r["n_seeds"] == 3 for r in rows)
    nc_runs = tmp_path / "multirun" / "neighbor_count"
    _study(nc_runs, shift_graf=0.0, shift_dl=0.0, L_values=(2, 4, 10))
    nc_record = tmp_path / {c["id"]: c for c in _claims()}["table5_L2_to_L4"]["record"]
    nc_record.parent.mkdir(parents=True)
    write_intervals(nc_runs, nc_record.parent)

    table = ledger(_claims(), tmp_path)
    by_id = {r["id"]: r for r in table}
    assert by_id["cross_scene_vs_knn"]["verdict"] == "holds"  # +0.6 dB, 120 spectra x 4 cells
    assert by_id["cross_scene_vs_knn_dl"]["verdict"] == "holds"  # +0.5 dB
    assert "conference_v2: +0.5" in by_id["cross_scene_vs_knn_dl"]["platform"]
    assert by_id["table5_L2_to_L4"]["verdict"] == "holds"
    assert abs(float(by_id["table5_L2_to_L4"]["platform"]) - 1.5) < 0.05
    assert by_id["table5_plateau"]["verdict"] == "holds"  # L = 4 and 10 equal up to noise
    assert by_id["table1_bedroom"]["verdict"] == "not reproduced"  # no unseen-layouts record in the fixture
    assert "no record yet" in by_id["table1_bedroom"]["reason"]
    assert by_id["table6_size"]["verdict"] == "not comparable"
    # issue 53's targets on the same cells: +0.6 dB is short of 1.0; better on nearly every spectrum is past 80%
    assert (
        by_id["target_matrix_margin"]["verdict"] == "not reproduced"
        and "(missed by 0.4" in by_id["target_matrix_margin"]["reason"]
    )
    assert by_id["target_matrix_share"]["verdict"] == "holds"

    out = tmp_path / "sweeps" / "claims"
    out.mkdir(parents=True)
    (out / "dropped_claim.png").write_bytes(b"png")  # a figure of a claim no longer in the ledger
    write_ledger(_claims(), table, tmp_path, out)
    with open(out / "claims.csv", newline="") as f:
        back = list(csv.DictReader(f))
    assert [r["id"] for r in back] == [r["id"] for r in table] and back[0]["verdict"] == table[0]["verdict"]
    text = (out / "claims.md").read_text()
    assert "Verdict: **holds**" in text and "| conference_v1 -> conference_v2 | +0.5" in text
    # a figure per claim whose record holds its cells, none for a claim without a record, the stale one gone
    figures = {p.name for p in out.glob("*.png")}
    assert figures == {"cross_scene_vs_knn_dl.png", "cross_scene_vs_knn.png", "table5_L2_to_L4.png",
                       "table5_plateau.png", "target_matrix_margin.png", "target_matrix_share.png"}  # fmt: skip
    assert "![" in text and "(sweeps/claims/table5_L2_to_L4.png)" in text


def _matrix_ledger(runs, root) -> dict:
    """The ledger's rows by id, with ``runs``' intervals published as the paper-density matrix under ``root``."""
    out = _matrix_record(root)
    out.mkdir(parents=True)
    write_intervals(runs, out)
    return {r["id"]: r for r in ledger(_claims(), root)}


def _matrix_record(root):
    """The folder the ledger reads the paper-density matrix from (claims.yaml), under ``root``."""
    return root / {c["id"]: c for c in _claims()}["cross_scene_vs_knn_dl"]["record"].rsplit("/", 1)[0]


def test_a_level_or_cut_down_study_is_not_called_a_win(tmp_path):
    runs = tmp_path / "multirun" / "cross_scene_matrix"
    _study(runs, shift_graf=0.02, shift_dl=0.0)
    by_id = _matrix_ledger(runs, tmp_path)
    assert by_id["cross_scene_vs_knn_dl"]["verdict"] == "not reproduced"
    assert "interval includes 0" in by_id["cross_scene_vs_knn_dl"]["reason"]
    cut = tmp_path / "cut"
    _study(cut / "multirun", shift_graf=0.6, shift_dl=0.1, sim_num_tx=150)
    by_id = _matrix_ledger(cut / "multirun", cut)
    assert by_id["cross_scene_vs_knn"]["verdict"] == "not comparable"
    assert "150 positions" in by_id["cross_scene_vs_knn"]["reason"]


def test_a_same_family_claim_reads_its_pairs_alone(tmp_path):
    """conference_v1 -> office_v2 is zero-shot but across families: GRaF behind KNN-DL there must not refute the
    same-family claim, and the platform column names each pair."""
    runs = tmp_path / "multirun" / "cross_scene_matrix"
    _study(runs, shift_graf=0.6, shift_dl=0.1)
    _study(runs / "cross", shift_graf=-0.6, shift_dl=0.1, scenes={"conference_v1": ["office_v2"]})
    by_id = _matrix_ledger(runs, tmp_path)
    assert by_id["cross_scene_vs_knn_dl"]["verdict"] == "holds"
    assert "office_v1 -> office_v3: +0.5" in by_id["cross_scene_vs_knn_dl"]["platform"]
    assert "-> office_v2: -" not in by_id["cross_scene_vs_knn_dl"]["platform"].replace("office_v1 -> office_v2", "")
    assert by_id["cross_scene_vs_knn"]["verdict"] == "refuted"  # every zero-shot cell: conference_v1 -> office_v2


def test_the_published_ledger_is_what_the_published_records_give():
    """sweeps/claims/claims.csv (the docs page includes its .md) is graf-claims over the repository's records: a
    record changed without re-running graf-claims fails here."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    with open(root / "sweeps" / "claims" / "claims.csv", newline="") as f:
        published = list(csv.DictReader(f))
    assert published == ledger(_claims(), root)


def test_a_target_row_judges_a_ratio_against_its_own_figure_and_says_by_how_much():
    """An issue's target (``against``) read as the ratio of two figures of a record (``over``): below the target
    the row says by how much it missed, and a lower-is-better target holds at or below its figure."""
    from graf.reports.claims.judge import judge_value

    record = {"rows": [{"s": 1.0, "slow": 2.5}, {"s": 1.5}]}
    faster = {"key": "rows.1.s", "over": "rows.0.s", "paper_value": 3.0, "against": "the target's"}
    row = judge_value(faster, record)
    assert row["platform"] == "1.50" and row["verdict"] == "not reproduced"
    assert row["reason"] == "1.50 against the target's 3.00 (missed by 1.50)"
    calm = {"key": "rows.0.slow", "paper_value": 2.5, "higher_is_better": False}
    assert judge_value(calm, record)["verdict"] == "holds"
    assert judge_value({**calm, "over": "rows.9.s"}, record)["verdict"] == "not reproduced"  # no such row


def test_a_paired_target_judges_each_cell_against_a_margin_or_a_share_of_spectra_and_says_by_how_much():
    """Issue 53's matrix targets: ahead of KNN by at least 1.0 dB in every cell (interval excluding 0), and better on
    at least 80% of each cell's spectra; short of either, the row names the cell furthest short and by how much."""
    from graf.reports.claims.judge import judge_paired
    from graf.reports.statistics import paired_difference

    ids = range(40)
    ref = [{i: 20.0 + 0.1 * i for i in ids}]
    big = [{i: 21.5 + 0.1 * i + (0.2 if i % 2 else -0.2) for i in ids}]  # +1.5 dB, better on every spectrum
    small = [{i: 20.0 + 0.1 * i + (0.9 if i % 4 else -0.3) for i in ids}]  # +0.6 dB, better on 30 of 40
    assert paired_difference(small, ref, "psnr")["share_ahead"] == 0.75
    assert paired_difference(ref, small, "psnr")["share_ahead"] == 0.25
    lower = [{i: -v for i, v in small[0].items()}]  # lower is better for MSE: the share follows the metric
    assert paired_difference(lower, [{i: -v for i, v in ref[0].items()}], "mse")["share_ahead"] == 0.75
    row = lambda cell, runs: {  # noqa: E731
        "trained_on": "conference_v1", "eval_scene": cell, "method": "g", "metric": "psnr",
        "vs_knn": paired_difference(runs, ref, "psnr"),
    }  # fmt: skip
    data = {"rows": [row("conference_v2", big), row("conference_v3", small)]}
    claim = {"method": "g", "reference": "knn", "metric": "psnr", "margin": 1.0}
    out = judge_paired(claim, data)
    assert out["verdict"] == "not reproduced" and "1 of 2 cells reach the target's +1.00" in out["reason"]
    assert "furthest short: conference_v1 -> conference_v3, +0.60 (missed by 0.40)" in out["reason"]
    assert judge_paired({**claim, "margin": 0.5}, data)["verdict"] == "holds"
    share = judge_paired({**claim, "margin": None, "share": 0.8}, data)
    assert share["platform"] == "conference_v1 -> conference_v2: 100%; conference_v1 -> conference_v3: 75%"
    assert share["verdict"] == "not reproduced" and "(missed by 5 points)" in share["reason"]
    assert judge_paired({**claim, "margin": None, "share": 0.75}, data)["verdict"] == "holds"
    import pytest

    from graf.errors import ConfigError

    with pytest.raises(ConfigError, match="give margin or share, not both"):  # neither is silently dropped
        judge_paired({**claim, "share": 0.8}, data)
    # the ledger page's table of a share target shows each cell's share beside its difference
    from graf.reports.claims.judge import paired_cells
    from graf.reports.claims.ledger import platform

    shared = {**claim, "margin": None, "share": 0.8, "title": "t", "kind": "paired"}
    text = platform(shared, share, paired_cells(shared, data), None)
    assert "| better on (share of spectra) |" in text and "| conference_v1 -> conference_v3 | +0.60 |" in text
    assert text.rstrip().endswith("| 75% |")


SUMMARY = re.compile(r"^- \*\*(holds|refuted|not reproduced|not comparable)\*\* \((\d+)\): (.*)$", re.M)
SECTION = re.compile(r"^##+ (.+) \{#(\w+)\}$", re.M)  # a claim's section (##) and its re-runs' parts (###)
MAX_CELL = 60  # characters in a table cell of the page: its tables fit the site's column
MAX_COLUMNS = 5


def test_the_published_ledger_page_is_a_summary_then_a_section_per_claim_with_its_figure():
    """sweeps/claims/claims.md, the page docs/claims.md shows: the summary's counts are the CSV's verdicts, every
    claim has its section (heading, verdict, command in a code block) and every comparison its forest plot; no
    table is wider than the column; the page is what graf-claims writes from the records today."""
    from pathlib import Path

    from graf.reports.claims import claim_cells
    from graf.reports.claims.ledger import page

    root = Path(__file__).resolve().parents[2]
    out = root / "sweeps" / "claims"
    with open(out / "claims.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    whole = (out / "claims.md").read_text()
    claims = _claims()
    found = {c["id"] for c in claims if c["kind"] == "distance"}  # findings beyond the paper: their own part
    text, _, findings = whole.partition("## Findings beyond the paper {#findings}")
    assert findings and [i for _, i in SECTION.findall(findings)] == [r["id"] for r in rows if r["id"] in found]
    said = {v: int(n) for v, n in re.findall(r"^- \*\*([a-z ]+)\*\* \((\d+)\):", findings, re.M)}
    assert said == {v: sum(r["verdict"] == v for r in rows if r["id"] in found) for v in FINDING_VERDICTS}
    rows = [r for r in rows if r["id"] not in found]
    rerun = {c["id"]: c["of"] for c in claims if c.get("of")}  # a re-run of a claim: a part of its section
    counts, bases = Counter(), [r for r in rows if r["id"] not in rerun]
    for verdict, n, named in SUMMARY.findall(text):
        counts[verdict] += int(n)  # claims, not runs: a re-run is named beside its claim, not counted
        linked = re.findall(r"\]\(#(\w+)\)", named)
        assert len([i for i in linked if i not in rerun]) == int(n)
        assert all(rerun[i] in linked for i in linked if i in rerun)
    assert counts == Counter(r["verdict"] for r in bases) and sum(counts.values()) == len(bases)
    order = [i for b in bases for i in [b["id"], *(r["id"] for r in rows if rerun.get(r["id"]) == b["id"])]]
    assert [i for _, i in SECTION.findall(text)] == order
    by_id = {r["id"]: r for r in rows}
    for part in re.split(r"^##+ ", text, flags=re.M)[1:]:
        r = by_id[re.search(r"\{#(\w+)\}", part).group(1)]
        assert f"Verdict: **{r['verdict']}**." in part and (not r["command"] or "```bash\n" in part)
        if r["interval"]:  # a comparison: its cells' table and its forest plot, drawn and shown
            assert (out / f"{r['id']}.png").is_file() and f"](sweeps/claims/{r['id']}.png)" in part
            assert "| 95% interval |" in part
    for line in (x for x in whole.splitlines() if x.startswith("|")):
        cells = [c.strip() for c in line.strip("|").split(" | ")]
        assert len(cells) <= MAX_COLUMNS and max(map(len, cells)) <= MAX_CELL, line
    with open(out / "claims.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert whole == page(claims, rows, {c["id"]: claim_cells(c, root) for c in claims}, root, out)


def test_the_claims_page_cites_the_paper_and_shows_the_ledger():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "claims.md").read_text()
    title = "Generalizable Radio-Frequency Radiance Fields for Spatial Spectrum Synthesis"
    assert title in text and "CVPR 2026" in text and "2502.05708" in text
    assert "../shared" not in text and "<!-- gen: include sweeps/claims/claims.md -->" in text


def test_a_long_command_is_wrapped_into_lines_that_read_as_the_same_command():
    from graf.reports.claims.ledger import wrap

    command = "graf-bench threads=2 " + " ".join(f"'+model@models.m{i}=graf_cpu_scenes_ray_weights'" for i in range(4))
    lines = wrap(command, width=60).splitlines()
    assert len(lines) > 1 and all(len(x) <= 60 for x in lines)
    assert all(x.endswith(" \\") for x in lines[:-1]) and all(x.startswith("    ") for x in lines[1:])
    assert " ".join(x.removesuffix(" \\").strip() for x in lines) == command
    assert wrap("graf-bench") == "graf-bench"


def _claims_command(monkeypatch, capsys, *args):
    """graf-claims' exit code and stderr's lines (the log's own lines left out)."""
    from graf.cli import claims as graf_claims
    from tests.app.test_entry_points import _main

    code, _, err = _main(monkeypatch, capsys, graf_claims.main, *args)
    return code, [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("[")], err


def test_a_users_claims_file_is_read_or_refused_in_one_line_never_replaced_by_graf_own(tmp_path, monkeypatch, capsys):
    """A claims.yaml in a --config-dir (which graf's own file of that name hides from Hydra) or claims=<file>: a
    malformed one stops with one line naming it, a good one is the ledger's (with its records and method), and a
    records folder that does not exist stops too; nothing of an earlier ledger in ``out`` is lost."""
    out = tmp_path / "ledger"
    out.mkdir()
    (out / "claims.csv").write_text("an earlier ledger\n")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "claims.yaml").write_text("claims:\n  - id: x\n    kind: [unclosed\n")
    run = ("out=" + str(out), f"hydra.run.dir={tmp_path / 'logs'}")
    for args in (("--config-dir", str(bad)), (f"claims={bad / 'claims.yaml'}",)):
        code, lines, err = _claims_command(monkeypatch, capsys, *args, *run)
        assert code == 2 and "Traceback" not in err, err
        assert lines[0].startswith(f"error: {bad / 'claims.yaml'}: not a readable claims file ("), err
    lacking = tmp_path / "lacking.yaml"
    lacking.write_text("claims:\n  - id: x\n    kind: value\n    record: r.json\n")
    code, lines, _ = _claims_command(monkeypatch, capsys, f"claims={lacking}", *run)
    assert code == 2 and lines[0] == f"error: {lacking}: claim 'x' (kind value) lacks key, paper_value"
    code, lines, _ = _claims_command(monkeypatch, capsys, f"records={tmp_path / 'nowhere'}", *run)
    assert code == 2 and lines[0].startswith(f"error: records={tmp_path / 'nowhere'}: no such folder"), lines
    assert (out / "claims.csv").read_text() == "an earlier ledger\n"  # nothing written by a refused command
    good = tmp_path / "good"
    good.mkdir()
    (tmp_path / "r.json").write_text(json.dumps({"figure": 2.5}))
    claim = "{id: mine, kind: value, record: r.json, key: figure, paper_value: 2.0, claim: '${method} says'}"
    (good / "claims.yaml").write_text(f"records: {tmp_path}\nmethod: m1\nclaims:\n  - {claim}\n")
    code, lines, err = _claims_command(monkeypatch, capsys, "--config-dir", str(good), *run)
    assert code is None, err
    with open(out / "claims.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["id"], r["claim"], r["verdict"]) for r in rows] == [("mine", "m1 says", "holds")]


def test_a_value_claim_with_runs_is_judged_on_its_interval_not_on_its_mean(tmp_path):
    """A figure above the paper's whose interval over the test spectra still reaches below it is not reproduced
    (issue 68: 22.94 against 21.94 on 40 spectra, one run); with its runs' interval clear of it, it holds; two runs'
    per-spectrum values are averaged and the interval widened to each run's own figure."""
    rng = np.random.default_rng(0)

    def run(folder, values):
        folder.mkdir(parents=True)
        (folder / "results.json").write_text(json.dumps({"method": "graf", "metrics": {"test/psnr": values.mean()}}))
        rows = [{"eval_scene": "s", "method": "graf", "id": i, "mse": 0.01, "psnr": v, "ssim": 0.5, "lpips": 0.2}
                for i, v in enumerate(values)]  # fmt: skip
        write_per_spectrum(folder / "per_spectrum.csv.gz", rows)

    run(tmp_path / "wide", 22.94 + np.tile([6.5, -6.5], 20))  # mean 22.94, spread wide enough to reach 21.94
    run(tmp_path / "tight", 22.94 + rng.normal(0, 0.5, 40))
    second = 22.60 + rng.normal(0, 0.5, 40)
    run(tmp_path / "tight2", second)
    claim = {"id": "rfid", "kind": "value", "key": "metrics.test/psnr", "paper_value": 21.94}
    rows = ledger(
        [
            {**claim, "id": "one_wide", "record": "wide/results.json", "seeds": ["wide/results.json"]},
            {**claim, "id": "one_tight", "record": "tight/results.json", "seeds": ["tight/results.json"]},
            {
                **claim,
                "id": "two",
                "record": "tight/results.json",
                "seeds": ["tight/results.json", "tight2/results.json"],
            },
            {**claim, "id": "no_runs", "record": "wide/results.json"},  # the figure alone, as before
        ],
        tmp_path,
    )
    by = {r["id"]: r for r in rows}
    low, high = (float(x) for x in by["one_wide"]["interval"].strip("[]").split(", "))
    assert by["one_wide"]["platform"] == "22.94" and low < 21.94 < 22.94 < high
    assert (
        by["one_wide"]["verdict"] == "not reproduced" and "does not clear the paper's 21.94" in by["one_wide"]["reason"]
    )
    assert by["one_tight"]["verdict"] == "holds" and "1 run over 40 test spectra" in by["one_tight"]["reason"]
    two_low = float(by["two"]["interval"].strip("[]").split(", ")[0])
    assert "2 runs" in by["two"]["reason"] and two_low <= second.mean()  # widened to each run's own figure
    assert by["no_runs"]["verdict"] == "holds" and by["no_runs"]["interval"] == ""


def test_every_command_of_the_ledger_runs_when_pasted():
    """The ledger's command blocks hold exact shell lines (bash -n parses them, no ``<placeholder>`` in them); the
    form of each job a study runs, with its placeholders, is said beside, not in the block."""
    import shutil
    import subprocess

    from graf.reports.claims.ledger import shell_lines

    lines, jobs = shell_lines(
        "GRAF_NC_L=2,4 bash s.sh nc; GRAF_NC_L=6 bash s.sh nc (graf-train model=<a | b> x=(1)); graf-report runs=r"
    )
    assert lines == ["GRAF_NC_L=2,4 bash s.sh nc", "GRAF_NC_L=6 bash s.sh nc", "graf-report runs=r"]
    assert jobs == "graf-train model=<a | b> x=(1)"
    assert shell_lines("graf-bench threads=2") == (["graf-bench threads=2"], None)
    bash = shutil.which("bash")
    for claim in _claims():
        if not claim.get("command"):
            continue
        lines, _ = shell_lines(str(claim["command"]))
        assert lines and not any("<" in line for line in lines), claim["id"]
        if bash:
            p = subprocess.run([bash, "-n"], input="\n".join(lines), capture_output=True, text=True)
            assert p.returncode == 0, f"{claim['id']}: {p.stderr}"


def test_a_slice_is_not_comparable_and_an_untrusted_timing_is_said():
    """The page's own definitions: a record made on the embedded slice of a real scene is below the paper's
    density (not comparable); a bench timing its record marks disturbed is named in the verdict's reason."""
    from graf.reports.claims.records import density_reason, untrusted_timings

    sliced = {
        "n_train": 160,
        "n_test": 40,
        "config": {"scene": {"rfid_s23": {"name": "rfid_s23", "path": "embedded:x"}}},
    }
    assert density_reason(sliced) == "made on the embedded 200-position slice of rfid_s23 (the paper: the whole scene)"
    assert density_reason({"config": {"scene": {"c": {"name": "c", "path": "data/c"}}}}) is None
    bench = {"rows": [
        {"preset": "graf", "scene": "c1", "disturbances": ["infer: spread 18% (limit 15%)", "train: load 0.4 cores"]},
        {"preset": "nerf2", "scene": "c1", "disturbances": []},
    ]}  # fmt: skip
    claim = {"key": "rows.0.infer_s_per_spectrum", "over": "rows.1.infer_s_per_spectrum"}
    assert untrusted_timings(claim, bench) == ["graf on c1: infer: spread 18% (limit 15%)"]  # its phase's only
    assert untrusted_timings({"key": "rows.1.train_s_per_step"}, bench) == []
    assert untrusted_timings({"key": "metrics.test/psnr"}, bench) == []


def test_a_rerun_must_name_an_earlier_claim():
    import pytest

    from graf.errors import ConfigError
    from graf.reports.claims.claims_file import check_claims

    base = {"id": "a", "kind": "note", "reason": "r"}
    check_claims([base, {"id": "b", "kind": "note", "reason": "r", "of": "a"}])
    for bad in ({"of": "z"}, {"of": "b"}):  # unknown; a re-run of a re-run
        with pytest.raises(ConfigError, match="must name an earlier claim"):
            check_claims(
                [
                    base,
                    {"id": "b", "kind": "note", "reason": "r", "of": "a"},
                    {"id": "c", "kind": "note", "reason": "r", **bad},
                ]
            )
