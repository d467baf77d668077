"""The ledger's findings beyond the paper (graf.reports.claims.findings): a neighbour-distance record judged per
(family, distance) with its intervals, a verdict that says where the method leads, trails or is level, its own part
of the page counted apart from the paper's claims, and "not run yet" without a record."""

from __future__ import annotations

import json

from graf.reports.claims import ledger, write_ledger


def _c(diff, verdict):
    return {"diff": diff, "low": diff - 0.1, "high": diff + 0.1, "verdict": verdict, "n_seeds": 3}


def _finding(fid, method, reference, record="study/distance.json"):
    return {"id": fid, "title": f"{method} against {reference}", "claim": f"{method} minus {reference}.",
            "kind": "distance", "record": record, "method": method, "reference": reference, "metric": "psnr",
            "command": "graf-report runs=study"}  # fmt: skip


def test_a_distance_finding_says_where_a_method_leads_trails_or_is_level_and_stands_apart(tmp_path):
    record = {
        "differences": {
            "conference_v1": {
                "0.0": {"graf": {"vs_knn": _c(-0.3, "behind"), "vs_knn-dl": _c(0.0, "level")},
                        "knn-dl": {"vs_knn": _c(0.0, "level")}},
                "4.0": {"graf": {"vs_knn": _c(1.2, "ahead"), "vs_knn-dl": _c(0.0, "level")},
                        "knn-dl": {"vs_knn": _c(0.4, "ahead")}},
            },
            "office_v1": {
                "0.0": {"graf": {"vs_knn": _c(0.0, "level"), "vs_knn-dl": _c(-0.5, "behind")},
                        "knn-dl": {"vs_knn": _c(0.0, "level")}},
                "4.0": {"graf": {"vs_knn": _c(0.9, "ahead"), "vs_knn-dl": _c(0.0, "level")},
                        "knn-dl": {"vs_knn": _c(0.2, "ahead")}},
            },
        }
    }  # fmt: skip
    (tmp_path / "study").mkdir()
    (tmp_path / "study" / "distance.json").write_text(json.dumps(record))
    claims = [
        {"id": "paper_claim", "title": "A claim of the paper", "source": "Table 1", "claim": "x", "paper": "y",
         "kind": "value", "record": "missing/results.json", "key": "metrics.test/psnr", "paper_value": 1.0},
        _finding("graf_vs_knn", "graf", "knn"),
        _finding("graf_vs_knn_dl", "graf", "knn-dl"),
        _finding("dl_vs_knn", "knn-dl", "knn"),
        _finding("not_yet", "graf", "knn", record="later/distance.json"),
    ]  # fmt: skip
    rows = {r["id"]: r for r in ledger(claims, tmp_path)}
    assert rows["graf_vs_knn"]["verdict"] == "mixed"  # behind at 0 on conference_v1, ahead at 4 in both
    assert "Ahead (95% interval above 0): conference_v1 at 4 λ; office_v1 at 4 λ" in rows["graf_vs_knn"]["reason"]
    assert "Behind (95% interval below 0): conference_v1 at 0 λ" in rows["graf_vs_knn"]["reason"]
    assert rows["graf_vs_knn"]["platform"].startswith("conference_v1, 0 λ: -0.30; conference_v1, 4 λ: +1.20")
    assert rows["graf_vs_knn_dl"]["verdict"] == "trails" and rows["dl_vs_knn"]["verdict"] == "leads"
    assert rows["not_yet"]["verdict"] == "not run yet" and rows["paper_claim"]["verdict"] == "not reproduced"
    out = tmp_path / "ledger"
    write_ledger(claims, list(rows.values()), tmp_path, out)
    result = json.loads((out / "results.json").read_text())
    assert result["counts"]["not reproduced"] == 1 and sum(result["counts"].values()) == 1  # the claims alone
    assert result["findings"] == {"leads": 1, "trails": 1, "level": 0, "mixed": 1, "not run yet": 1}
    page = (out / "claims.md").read_text()
    claims_part, _, findings = page.partition("## Findings beyond the paper {#findings}")
    assert "paper_claim" in claims_part and "graf_vs_knn" not in claims_part  # the summary counts claims alone
    assert "- **mixed** (1): [graf against knn](#graf_vs_knn)" in findings
    assert "### graf against knn {#graf_vs_knn}" in findings and "*Not a claim of the paper.*" in findings
    assert (out / "graf_vs_knn.png").is_file() and "| conference_v1, 4 λ | +1.20 | [+1.10, +1.30] |" in findings


def test_findings_and_paired_claims_share_one_cell_shape_and_one_pair_of_columns():
    from graf.reports.claims.cells import cell, columns

    plain = cell("conference_v1, 4 λ", _c(1.2, "ahead"))
    shared = cell("a -> b", {**_c(-0.25, "behind"), "share_ahead": 0.4})
    assert plain == {
        "cell": "conference_v1, 4 λ",
        **{k: _c(1.2, "ahead")[k] for k in ("diff", "low", "high", "verdict")},
    }
    assert shared["share_ahead"] == 0.4 and "n_seeds" not in shared  # the record's other keys stay out
    assert columns([plain, shared]) == {
        "platform": "conference_v1, 4 λ: +1.20; a -> b: -0.25",
        "interval": "conference_v1, 4 λ: [+1.10, +1.30]; a -> b: [-0.35, -0.15]",
    }
