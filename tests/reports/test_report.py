"""graf-report on small study folders: every table and figure, with the numbers of the results.json files
in them (handmade results of known values; tests/studies/test_studies.py runs a real study end to end)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from graf.app.config import CONF_DIR
from graf.errors import ConfigError
from graf.io import atomic_write_json
from graf.reports.published import study_tables
from graf.reports.rows import short_scenes
from graf.reports.study import make_report, report

GHZ24, MHZ915 = 2.412e9, 915e6
REFERENCE = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "report.yaml").reference)  # the spectra grids' jobs


def _metrics(psnr: float) -> dict:
    return {"test/psnr": psnr, "test/ssim": psnr / 100, "test/lpips": 1 - psnr / 100, "test/mse": 10 ** (-psnr / 10)}


def _result(
    folder: Path,
    method: str,
    trained: list[str],
    evals: list[tuple],
    L: int = 10,
    finetune=None,
    knn: dict | None = None,
    train_hz: float = GHZ24,
    steps: int = 300,
) -> None:
    """A results.json as graf-train writes it (the keys graf-report reads); ``evals``: (scene, psnr, band_hz)."""
    r = {
        "method": method,
        "train_scenes": trained,
        "train_bands_hz": [train_hz],
        "global_step": steps,
        "config": {"neighbors": {"L": L}},
        "finetune": finetune,
        "evaluations": [
            {
                "eval_scene": s,
                "within_scene": s in trained,
                "metrics": _metrics(p),
                "n_test": 30,
                "band_hz": hz,
                "baselines": {"knn": {"metrics": _metrics(knn[s])}} if knn else {},
            }
            for s, p, hz in evals
        ],
    }
    folder.mkdir(parents=True)
    atomic_write_json(folder / "results.json", r)


def _samples(folder: Path, scene: str, method: str, value: int, n: int = 2) -> None:
    (folder / "samples").mkdir(parents=True, exist_ok=True)
    t = np.full((n, 90, 360), 100, np.uint8)
    ids = np.arange(3, 3 + 2 * n, 2)
    np.savez(folder / "samples" / f"{scene}__{method}.npz", pred=np.full_like(t, value), target=t, ids=ids)


def test_cross_scene_matrix_tables_heatmaps_and_spectra(tmp_path):
    knn = {"a_v1": 15.0, "a_v2": 14.0, "b_v1": 13.0}
    scenes = ("a_v1", "a_v2", "b_v1")
    _result(tmp_path / "j0", "graf", ["a_v1"], [(s, p, GHZ24) for s, p in zip(scenes, (20.0, 18.0, 12.0))], knn=knn)
    _result(tmp_path / "j1", "graf", ["b_v1"], [(s, p, GHZ24) for s, p in zip(scenes, (11.0, 10.5, 19.0))], knn=knn)
    _result(tmp_path / "j2", "nerf2", ["a_v1"], [("a_v1", 16.0, GHZ24), ("a_v2", 4.0, GHZ24), ("b_v1", 3.0, GHZ24)])
    _result(tmp_path / "base" / "x", "graf", ["zzz"], [("zzz", 99.0, GHZ24)])  # a study's base model: left out
    _samples(tmp_path / "j0", "a_v2", "graf", 110)
    _samples(tmp_path / "j0", "a_v2", "knn", 150)
    s = make_report(tmp_path, tmp_path / "out", REFERENCE)
    assert s["n_results"] == 3 and s["axes"] == ["trained_on", "eval_scene"]
    m = s["matrix"]
    assert m["graf"]["PSNR"]["rows"] == ["a_v1", "b_v1"] and m["graf"]["PSNR"]["cols"] == ["a_v1", "a_v2", "b_v1"]
    assert m["graf"]["PSNR"]["values"] == [[20.0, 18.0, 12.0], [11.0, 10.5, 19.0]]
    assert m["nerf2"]["PSNR"]["values"][0] == [16.0, 4.0, 3.0] and np.isnan(m["nerf2"]["PSNR"]["values"][1]).all()
    assert m["knn"]["PSNR"]["values"] == [[15.0, 14.0, 13.0]]  # tested in two jobs on the same data: once
    assert m["graf"]["LPIPS"]["values"][0][0] == pytest.approx(0.8)
    for name in ("matrix_psnr.png", "matrix_ssim.png", "matrix_lpips.png", "matrix_mse.png", "spectra_a_v2.png"):
        assert (tmp_path / "out" / name).stat().st_size > 5000
    rows = list(csv.DictReader((tmp_path / "out" / "report.csv").open()))
    assert len(rows) == 3 + 3 + 3 + 3  # graf x 2 training scenes, nerf2, knn: 3 test scenes each
    g = [r for r in rows if r["method"] == "graf" and r["trained_on"] == "b_v1" and r["eval_scene"] == "a_v2"]
    assert len(g) == 1 and float(g[0]["PSNR"]) == 10.5 and g[0]["n_test"] == "30" and g[0]["steps"] == "300"
    assert g[0]["seeds"] == "1"
    md = (tmp_path / "out" / "report.md").read_text()
    assert "| b_v1 | a_v2 | graf | 30 | 1 | 300 | 0.0891 | 10.50 | 0.105 | 0.895 |" in md
    tex = (tmp_path / "out" / "report.tex").read_text()
    assert (
        r"b\_v1 & a\_v2 & graf & 30 & 1 & 300 & 0.0891 & 10.50 & 0.105 & 0.895 &  \\" in tex
    )  # reliance: not in these rows


def test_a_cell_of_two_seeds_shows_their_mean_in_every_table_and_heatmap(tmp_path):
    """Two seeds' jobs in one cell: the table, the heatmap's matrix, the README's tables and the per-pair table
    show the mean of the two, never the last job's figure (the old generator wrote each job into its cell in
    turn, so the second seed's 19.0 stood for the cell)."""
    for seed, psnr in ((0, 21.0), (1, 19.0)):
        _result(tmp_path / f"s{seed}", "graf", ["a_v1"], [("a_v1", psnr, GHZ24), ("a_v2", psnr - 4, GHZ24)],
                knn={"a_v1": 15.0, "a_v2": 14.0})  # fmt: skip
    _result(
        tmp_path / "b",
        "graf",
        ["b_v1"],
        [("a_v1", 10.0, GHZ24), ("a_v2", 11.0, GHZ24)],
        knn={"a_v1": 15.0, "a_v2": 14.0},
    )  # fmt: skip  (a second training scene: a matrix of two rows)
    s = make_report(tmp_path, tmp_path / "out", REFERENCE)
    m = s["matrix"]["graf"]
    assert m["PSNR"]["values"] == [[20.0, 16.0], [10.0, 11.0]] and m["PSNR"]["seeds"] == [[2, 2], [1, 1]]
    assert m["SSIM"]["values"][0][0] == pytest.approx(0.20)  # each figure its own mean
    assert s["matrix"]["knn"]["PSNR"]["values"] == [[15.0, 14.0]]
    assert "mean over 1-2 seeds a cell" in (tmp_path / "out" / "README.md").read_text()
    rows = list(csv.DictReader((tmp_path / "out" / "report.csv").open()))
    g = [r for r in rows if r["method"] == "graf" and r["eval_scene"] == "a_v1" and r["trained_on"] == "a_v1"]
    assert len(g) == 1 and float(g[0]["PSNR"]) == 20.0 and g[0]["seeds"] == "2"
    readme = (tmp_path / "out" / "README.md").read_text()
    assert "| graf | a_v1 | 20.00 | 16.00 |" in readme
    assert "| graf | a_v1 | 19.00" not in readme and "| graf | a_v1 | 21.00" not in readme
    for seed, psnr in ((0, 21.0), (1, 19.0)):  # the same in the neighbour count's per-pair table
        _result(tmp_path / "nc" / f"s{seed}", "graf", ["a_v1"], [("a_v2", psnr, GHZ24)], L=4)
        _result(tmp_path / "nc" / f"t{seed}", "graf", ["a_v1"], [("a_v2", psnr + 1, GHZ24)], L=8)
    nc = make_report(tmp_path / "nc", tmp_path / "nc_out", REFERENCE)
    text = "\n".join(study_tables(nc, json.loads((tmp_path / "nc_out" / "rows.json").read_text())["rows"]))
    assert "| a_v2 | graf | a_v1 | 20.00 | 21.00 |" in text and "the mean over 2 seeds a cell" in text


def test_neighbor_count_curve_averages_the_same_family_pairs(tmp_path):
    for L, (c2, c3, o2) in {2: (10.0, 12.0, 5.0), 10: (20.0, 22.0, 6.0)}.items():
        # trained on a conference layout: tested on its family (averaged) and on another (left out of the curve)
        _result(
            tmp_path / f"L{L}",
            "graf",
            ["conference_v1"],
            [("conference_v2", c2, GHZ24), ("conference_v3", c3, GHZ24), ("office_v2", o2, GHZ24)],
            L=L,
        )
    s = make_report(tmp_path, tmp_path, REFERENCE)
    assert s["axes"] == ["L", "eval_scene"]
    assert s["vs_L"]["graf"][2]["PSNR"] == pytest.approx(11.0)
    assert s["vs_L"]["graf"][10]["PSNR"] == pytest.approx(21.0)
    assert s["vs_L"]["graf"][10]["n_pairs"] == 2
    assert (tmp_path / "vs_L.png").stat().st_size > 5000


def test_the_spectra_grids_show_the_reference_setting_of_conf_report(tmp_path):
    """Which job's spectra the grids show is conf/report.yaml's ``reference`` (L = 10 there), not a constant."""
    for L in (2, 10):
        _result(tmp_path / f"L{L}", "graf", ["conference_v1"], [("conference_v2", 20.0, GHZ24)], L=L)
    _samples(tmp_path / "L2", "conference_v2", "graf", 110)  # only the L = 2 job saved spectra

    def run(*overrides):
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            cfg = compose("report", overrides=[f"runs={tmp_path}", f"paths.output_dir={tmp_path}", *overrides])
        return report(cfg)["figures"]

    assert REFERENCE["L"] == 10 and "spectra_conference_v2.png" not in run()
    assert "spectra_conference_v2.png" in run("reference.L=2")


def test_a_record_of_validation_only_jobs_reports_without_spectra_grids(tmp_path):
    """A job run with test=false (a study's validation jobs) saves samples files without test spectra: the
    report is made, and draws no spectra grid for them (it used to fail on a grid of zero columns)."""
    _result(tmp_path / "v0", "graf", ["conference_v1"], [("conference_v4", 20.0, GHZ24)])
    _samples(tmp_path / "v0", "conference_v4", "graf", 110, n=0)
    _samples(tmp_path / "v0", "conference_v4", "knn", 150, n=0)
    s = make_report(tmp_path, tmp_path / "out", REFERENCE)
    assert s["n_results"] == 1 and not [f for f in s["figures"] if f.startswith("spectra_")]
    assert not list((tmp_path / "out").glob("spectra_*.png"))


def test_finetune_fraction_curves_and_band_matrix(tmp_path):
    base = {"conference_v1": {"index": 0, "band_hz": GHZ24}}
    for label, frac, psnr in (("zero-shot", None, 5.0), ("f20", 0.2, 12.0), ("f100", 1.0, 16.0)):
        ft = {
            "mode": "zero-shot" if frac is None else "fine-tune",
            "fraction": frac,
            "base_scenes": base,
            "base_steps": 300,
            "steps": 0 if frac is None else 100,
            "test_pool": "measured",
        }
        _result(tmp_path / "ft" / label, "graf", ["bedroom"], [("bedroom", psnr, GHZ24)], finetune=ft)
    s = make_report(tmp_path / "ft", tmp_path / "ft", REFERENCE)
    curve = s["vs_fraction"]["bedroom | trained at 2.412 GHz"]["graf"]
    assert {k: v["PSNR"] for k, v in curve.items()} == {0.0: 5.0, 0.2: 12.0, 1.0: 16.0}
    assert "| f20 | graf | 30 | 1 | 300+100 |" in (tmp_path / "ft" / "report.md").read_text()

    bands = tmp_path / "bands"
    for i, (th, name) in enumerate(((MHZ915, "915"), (GHZ24, "24"))):
        _result(
            bands / f"t{name}",
            "graf",
            ["conference_v1"],
            [("conference_v1", 20.0 - 5 * i, MHZ915), ("conference_v1", 10.0 + 5 * i, GHZ24)],
            train_hz=th,
        )
    s = make_report(bands, bands, REFERENCE)
    bm = s["band_matrix"]["graf"]
    assert bm["rows"] == ["915 MHz", "2.412 GHz"] and bm["cols"] == ["915 MHz", "2.412 GHz"]
    assert bm["psnr"] == [[20.0, 10.0], [15.0, 15.0]]
    assert (bands / "band_matrix.png").stat().st_size > 5000


def test_a_folder_without_results_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="no results.json under"):
        make_report(tmp_path, tmp_path, REFERENCE)
    with pytest.raises(ConfigError, match="does not exist"):
        make_report(tmp_path / "nope", tmp_path, REFERENCE)


def test_a_published_study_s_figures_are_redrawn_from_its_own_records(tmp_path):
    """scripts/redraw_study_figures.py: the figures again from rows.json and report.json alone (no job folders),
    the records untouched."""
    import subprocess
    import sys

    for L, psnr in ((2, 10.0), (4, 12.0), (10, 20.0)):
        _result(tmp_path / "runs" / f"L{L}", "graf", ["conference_v1"], [("conference_v2", psnr, GHZ24)], L=L)
    out = tmp_path / "published"
    make_report(tmp_path / "runs", out, REFERENCE)
    records = {f: (out / f).read_bytes() for f in ("rows.json", "report.json", "report.md")}
    (out / "vs_L.png").unlink()
    root = Path(__file__).resolve().parents[2]
    p = subprocess.run([sys.executable, str(root / "scripts" / "redraw_study_figures.py"), str(out), str(tmp_path)],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    assert (
        out / "vs_L.png"
    ).stat().st_size > 5000 and f"{out}: report.md, report.csv, report.tex, vs_L.png" in p.stdout
    assert "not a graf-report folder" in p.stdout  # tmp_path itself holds no report
    assert {f: (out / f).read_bytes() for f in records} == records


def test_a_spectra_panel_names_a_many_scene_training_set_by_count():
    """Six scene names in one panel title overlap the next panel's: more than two are given as a count."""
    assert short_scenes("conference_v1") == "conference_v1"
    assert short_scenes("conference_v1+office_v1") == "conference_v1+office_v1"
    assert short_scenes("+".join(f"s{i}" for i in range(6))) == "6 scenes"


def test_interval_tables_list_l_fractions_and_bands_in_numeric_order():
    from graf.reports.intervals import natural

    assert sorted(["10", "2", "4"], key=natural) == ["2", "4", "10"]
    fractions = ["f100", "f05", "zero-shot", "f50", "f20", "f10"]
    assert sorted(fractions, key=natural) == ["zero-shot", "f05", "f10", "f20", "f50", "f100"]
    assert sorted(["office_v1", "conference_v2"], key=natural) == ["conference_v2", "office_v1"]
    bands = ["915 MHz", "1.8 GHz", "2.412 GHz", "3 GHz"]
    assert sorted(["2.412 GHz", "915 MHz", "3 GHz", "1.8 GHz"], key=natural) == bands
