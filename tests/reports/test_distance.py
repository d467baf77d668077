"""The neighbour-distance study's report (graf.reports.distance): synthetic study jobs (three seeds of two GRaF modes
and KNN-DL, KNN beside them, two families of two test layouts, three distances) and validation jobs go through
graf-report; the record gives each family's paired differences on the pooled layouts, the mode chosen on
validation, the geometry, the distance from which each method leads, and the sentence built from them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from graf.reports.distance import GRAF, advice, between_learned, leads_from, validation_choice
from graf.reports.study import make_report
from graf.run.per_spectrum import write_per_spectrum

FAMILIES = {"conference_v1": ["conference_v2", "conference_v3"], "office_v1": ["office_v2", "office_v3"]}
IDS = list(range(300, 420))
BAND_HZ = 2.4e9
VAL_LAYOUTS = {"conference_v4": 0.05, "office_v4": -0.05}  # a validation job's layouts: around its mean
# method -> distance -> lift over KNN (dB): GRaF's ray_knn mode gains as neighbours thin out, ray_weights less;
# KNN-DL gains a little at 4 wavelengths only
LIFT = {
    "graf-ray-weights": {0.0: 0.0, 1.0: 0.4, 4.0: 0.8},
    "graf-ray-knn": {0.0: 0.0, 1.0: 0.6, 4.0: 1.5},
    "knn-dl": {0.0: 0.0, 1.0: 0.0, 4.0: 0.5},
}


def _result(method, seed, trained, distance, evaluations, metrics=None):
    return {
        "method": method,
        "scene": trained,
        "train_scenes": [trained],
        "train_bands_hz": [BAND_HZ],
        "band_hz": BAND_HZ,
        "metrics": metrics or {"test/psnr": 0.0},
        "config": {"seed": seed, "sim_num_tx": None, "neighbors": {"L": 10, "exclude_within": distance}},
        "per_spectrum": "per_spectrum.csv.gz",
        "evaluations": evaluations,
    }


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("neighbor_distance")
    rng = np.random.default_rng(5)
    for distance in (0.0, 1.0, 4.0):
        for trained, layouts in FAMILIES.items():
            knn = {s: rng.normal(18.0 - distance, 3.0, len(IDS)) for s in layouts}
            for method, lift in LIFT.items():
                for seed in (0, 1, 2):
                    _study_job(root, method, seed, trained, distance, knn, lift[distance], rng)
        for method in ("graf-ray-weights", "graf-ray-knn"):  # validation: ray_knn ahead from 1 wavelength on
            val = 20.0 + (0.3 if (method == "graf-ray-knn") == (distance > 0) else 0.0)
            job = root / "validation" / f"model={method},exclude_within={distance}"
            job.mkdir(parents=True)
            layouts = [{"eval_scene": s, "metrics": {"val/psnr": val + dv}} for s, dv in VAL_LAYOUTS.items()]
            result = _result(method, 0, "conference_v1", distance, layouts, {"val/psnr": val - 0.1})
            (job / "results.json").write_text(json.dumps({**result, "per_spectrum": None}))
    return root


def _study_job(root, method, seed, trained, distance, knn, lift, rng):
    """One job: the method (KNN plus ``lift`` plus noise) and KNN on the family's test layouts."""
    rows, evals = [], []
    for s, base in knn.items():
        mine = base + lift + rng.normal(0.0, 0.2, len(IDS))
        for m, values in ((method, mine), ("knn", base)):
            rows += [{"eval_scene": s, "method": m, "id": i, "mse": 10 ** (-v / 10), "psnr": v, "ssim": 0.5,
                      "lpips": 0.3} for i, v in zip(IDS, values)]  # fmt: skip
        used = {"median_m": 0.05 + 0.125 * distance, "median_wavelengths": 0.4 + distance, "n_targets": 120}
        evals.append({"eval_scene": s, "band_hz": BAND_HZ, "metrics": {}, "baselines": {},
                      "splits": {"nearest_neighbor_used": used}})  # fmt: skip
    job = root / f"model={method},scene={trained},exclude_within={distance},seed={seed}"
    job.mkdir()
    write_per_spectrum(job / "per_spectrum.csv.gz", rows)
    (job / "results.json").write_text(json.dumps(_result(method, seed, trained, distance, evals)))


def test_the_mode_is_chosen_on_the_validation_jobs_at_each_distance(study):
    choice = validation_choice(study)
    assert {d: c["mode"] for d, c in choice.items()} == {
        "0.0": "graf-ray-weights",
        "1.0": "graf-ray-knn",
        "4.0": "graf-ray-knn",
    }
    assert choice["1.0"]["val_psnr"] == pytest.approx({"graf-ray-knn": 20.3, "graf-ray-weights": 20.0})


def test_the_distance_record_pools_each_family_and_states_where_each_method_leads(study, tmp_path):
    out = tmp_path / "report"
    summary = make_report(study, out, {"L": 10, "finetune": "f20", "exclude_within": 1.0})
    assert "exclude_within" in summary["axes"] and "vs_distance.png" in summary["figures"]
    assert not any(f.startswith("matrix_") for f in summary["figures"])  # distances are not one matrix
    record = json.loads((out / "distance.json").read_text())
    conf = record["differences"]["conference_v1"]
    assert conf["1.0"][GRAF]["mode"] == "graf-ray-knn" and conf["0.0"][GRAF]["mode"] == "graf-ray-weights"
    c = conf["4.0"][GRAF]["vs_knn"]
    assert c["n_spectra"] == 2 * len(IDS) and c["n_seeds"] == 3  # both test layouts, paired, three seeds
    assert c["diff"] == pytest.approx(1.5, abs=0.05) and c["verdict"] == "ahead"
    assert conf["0.0"]["knn-dl"]["vs_knn"]["verdict"].startswith("level")
    t = record["thresholds"]
    assert t[GRAF]["vs_knn"] == {"conference_v1": 1.0, "office_v1": 1.0, "all": 1.0}
    assert t["knn-dl"]["vs_knn"]["all"] == 4.0
    assert t[GRAF]["vs_knn-dl"]["all"] == 1.0
    geo = {(g["trained_on"], g["exclude_within"], g["eval_scene"]): g for g in record["geometry"]}
    assert geo[("office_v1", "4.0", "office_v3")]["median_wavelengths"] == pytest.approx(4.4)
    assert record["wavelength_m"] == pytest.approx(299_792_458.0 / BAND_HZ)
    assert record["advice"] == (
        "If your nearest measurements are 1 wavelength (12 cm at these layouts' band) or farther from where you "
        "predict (tested up to 4 wavelengths), GRaF leads KNN in every family; GRaF leads KNN-DL from 1 wavelength "
        "(12 cm at these layouts' band); KNN-DL leads KNN from 4 wavelengths (50 cm at these layouts' band). Closer "
        "than 1 wavelength, no learned method leads KNN in every family: use KNN."
    )
    readme = (out / "README.md").read_text()
    assert "## Neighbour distance" in readme and record["advice"] in readme
    assert "conference_v2: 1.40 λ, 17.5 cm" in readme
    assert "- GRaF (the mode of each distance) over KNN: leads from 1 wavelength" in readme  # modes differ
    assert "- graf-ray-knn over KNN:" in readme  # and each mode on its own
    assert (out / "vs_distance.png").stat().st_size > 0


def test_leads_from_needs_every_larger_distance_and_the_advice_says_when_nothing_leads():
    def c(verdict):
        return {"verdict": verdict}

    points = {"0.0": {"m": {"vs_knn": c("ahead")}}, "1.0": {"m": {"vs_knn": c("level")}},
              "4.0": {"m": {"vs_knn": c("ahead")}}}  # fmt: skip
    assert leads_from(points, "m") == 4.0  # ahead at 0 but not at 1: it leads from 4 only
    assert leads_from({"0.0": {"m": {"vs_knn": c("behind")}}}, "m") is None
    none = {"thresholds": {GRAF: {"vs_knn": {"all": None}}, "knn-dl": {"vs_knn": {"all": None}}},
            "distances": ["0.0", "4.0"], "wavelength_m": 0.125}  # fmt: skip
    assert advice(none).startswith("Up to 4 wavelengths (50 cm at these layouts' band)")
    assert "nearest-neighbour mean" in advice(none)
    everywhere = {**none, "thresholds": {"knn-dl": {"vs_knn": {"all": 0.0}}}}
    assert advice(everywhere) == ("KNN-DL leads KNN at every distance tested (0 to 4 wavelengths).")


def test_a_study_of_one_fixed_mode_within_its_scene_shows_that_mode_and_the_geometry_of_single_runs(tmp_path):
    """experiment=neighbor_distance_rfid: one GRaF mode, no validation jobs, each job a single run tested within its
    training scene (no ``evaluations`` list: the geometry is read from the run's own ``splits``)."""
    rng = np.random.default_rng(7)
    root = tmp_path / "neighbor_distance_rfid"
    for distance in (0.0, 1.0):
        knn = rng.normal(16.0, 2.0, len(IDS))
        for method, lift in (("graf-ray-knn", 2.0 * distance), ("knn-dl", 0.0)):
            for seed in (0, 1, 2):
                mine = knn + lift + rng.normal(0.0, 0.2, len(IDS))
                rows = [{"eval_scene": "rfid_s23", "method": m, "id": i, "mse": 10 ** (-v / 10), "psnr": v,
                         "ssim": 0.5, "lpips": 0.3} for m, vs in ((method, mine), ("knn", knn))
                        for i, v in zip(IDS, vs)]  # fmt: skip
                job = root / f"model={method},exclude_within={distance},seed={seed}"
                job.mkdir(parents=True)
                write_per_spectrum(job / "per_spectrum.csv.gz", rows)
                used = {"median_m": 0.33 * distance + 0.01, "median_wavelengths": distance + 0.02, "n_targets": 120}
                result = {**_result(method, seed, "rfid_s23", distance, None), "eval_scene": "rfid_s23",
                          "band_hz": 915e6, "splits": {"nearest_neighbor_used": used}}  # fmt: skip
                del result["evaluations"]
                (job / "results.json").write_text(json.dumps(result))
    out = tmp_path / "report"
    make_report(root, out, {"L": 10, "finetune": "f20", "exclude_within": 1.0})
    record = json.loads((out / "distance.json").read_text())
    points = record["differences"]["rfid_s23"]
    assert points["1.0"][GRAF]["mode"] == "graf-ray-knn" and points["1.0"][GRAF]["chosen_on"] == "fixed"
    assert points["1.0"][GRAF]["vs_knn"]["verdict"] == "ahead" and points["0.0"][GRAF]["vs_knn"]["verdict"] != "ahead"
    assert record["within_scene"] and record["thresholds"][GRAF]["vs_knn"]["all"] == 1.0
    geo = {(g["exclude_within"], g["eval_scene"]): g for g in record["geometry"]}
    assert geo[("1.0", "rfid_s23")]["median_wavelengths"] == pytest.approx(1.02)
    readme = (out / "README.md").read_text()
    assert "graf-ray-knn (fixed before the runs)" in readme and "rfid_s23: 1.02 λ, 34.0 cm" in readme
    # one scene tested within itself: the advice speaks of the scene and its band, not of families and layouts
    assert record["advice"].startswith(
        "If your nearest measurements are 1 wavelength (33 cm at this scene's band) or farther from where you "
        "predict (tested up to 1 wavelength), GRaF leads KNN within the scene"
    )
    assert "family" not in record["advice"] and "layouts" not in record["advice"]
    assert "leads from 1 wavelength within the scene" in readme
    # the mode fixed before the runs is named wherever GRaF is, not "the mode of each distance"
    assert "- GRaF (graf-ray-knn, fixed before the runs) over KNN: leads from 1 wavelength" in readme
    assert "the mode of each distance" not in readme and "- graf-ray-knn over" not in readme  # said once


def test_where_both_learned_methods_lead_knn_the_advice_says_which_of_them_to_take():
    def cell(verdict):
        return {GRAF: {"vs_knn-dl": {"verdict": verdict}}}

    record = {
        "thresholds": {GRAF: {"vs_knn": {"all": 0.0}, "vs_knn-dl": {"all": None}}, "knn-dl": {"vs_knn": {"all": 0.0}}},
        "distances": ["0.0", "1.0", "4.0"],
        "wavelength_m": 0.125,
        "differences": {
            "conference_v1": {d: cell("ahead") for d in ("0.0", "1.0", "4.0")},
            "office_v1": {
                "0.0": cell("ahead"),
                "1.0": cell("level (interval includes 0)"),
                "4.0": cell("level (interval includes 0)"),
            },
        },  # fmt: skip
    }
    assert advice(record) == (
        "GRaF leads KNN in every family at every distance tested (0 to 4 wavelengths); KNN-DL leads KNN at every "
        "distance tested (0 to 4 wavelengths); against KNN-DL, GRaF is ahead at every distance tested in "
        "conference_v1's family and ahead at 0, level at 1 and 4 wavelengths in office_v1's family (4 of 6 cells "
        "ahead, 0 behind), so where both lead KNN, GRaF is the choice."
    )
    record["differences"]["office_v1"]["4.0"] = cell("behind")
    assert between_learned(record).endswith(
        "(4 of 6 cells ahead, 1 behind), so which of the two pays depends on the room"
    )
    level = {f: {d: cell("level (interval includes 0)") for d in p} for f, p in record["differences"].items()}
    assert between_learned({**record, "differences": level}).endswith("so either does")
    assert between_learned({**record, "differences": {}}) == ""
    record["thresholds"][GRAF]["vs_knn-dl"]["all"] = 0.0  # GRaF leads KNN-DL in every family: said as before
    assert "against KNN-DL" not in advice(record) and "GRaF leads KNN-DL at every distance tested" in advice(record)
