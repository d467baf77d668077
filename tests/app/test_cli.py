"""The commands, composed from the real configs and run on CPU on the embedded and tiny scenes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from graf.app.config import CONF_DIR, CONF_PATH, scene_band_config
from graf.app.spec import RunSpec
from graf.data.spectrum_set import DataFormatError
from graf.errors import ConfigError
from graf.reports.table import make_table
from graf.run.build import model_config_for_neighbors
from graf.run.evaluate import evaluate
from graf.run.train import train

RESULT_KEYS = {"method", "scene", "band_hz", "n_train", "n_test", "metrics", "seconds", "config", "splits"}
TEST_KEYS = {"test/mse", "test/psnr", "test/ssim", "test/lpips"}
METRIC_KEYS = (
    TEST_KEYS
    | {k.replace("test/", "val/") for k in TEST_KEYS}
    | {"test/psnr_swapped", "test/reliance_db", "val/psnr_swapped", "val/reliance_db"}
    | {"test/n_empty", "val/n_empty"}
)


def _results(cfg) -> dict:
    return json.loads((Path(cfg.paths.output_dir) / "results.json").read_text())


def test_commands_read_the_configs_shipped_in_the_package():
    """Every command reads pkg://graf.conf (what a wheel ships); conf/ in the checkout is a link to it."""
    assert CONF_PATH == "pkg://graf.conf"
    assert (Path(__file__).resolve().parents[2] / "conf").resolve() == CONF_DIR.resolve()
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="graf.conf", version_base="1.3"):
        names = sorted(f.stem for f in CONF_DIR.glob("*.yaml"))  # every command's root config
        assert {"train", "eval", "simulate", "bench", "curves", "report", "interp", "aoa"} <= set(names)
        for name in names:
            assert compose(config_name=name) is not None
        assert compose(config_name="eval").scene.rfid_s23._target_
    GlobalHydra.instance().clear()


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_every_config_group_option_composes():

    groups = ["scene", "eval_scene", "band", "neighbors", "model", "trainer", "logger", "experiment"]
    for config_name in ("train", "eval", "simulate"):
        for group in groups:
            for f in sorted((CONF_DIR / group).glob("*.yaml")):
                if config_name == "simulate" and group in ("eval_scene", "neighbors", "model", "trainer", "logger"):
                    continue
                if group == "experiment" and (config_name == "simulate") != f.stem.startswith("sim_"):
                    continue  # experiments named sim_* are graf-simulate's
                GlobalHydra.instance().clear()
                with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                    overrides = [f"{group}={f.stem}"] + (
                        [f"{group}.nerf2.path=x", "band=2.4ghz"]
                        if f.stem == "nerf2" and group in ("scene", "eval_scene")
                        else []
                    )
                    cfg = compose(config_name=config_name, overrides=overrides)
                spec = RunSpec.of(cfg)
                (scene,) = spec.scenes
                assert scene._target_ and instantiate(scene_band_config(scene, cfg.get("band"))).frequency_hz > 0
                if group in ("scene", "eval_scene"):  # every option also builds its object
                    # same / heldout name no scene themselves (heldout: the sweeps' held-out layouts, resolved
                    # from the training scenes; tested in test_optuna_sweeper.py)
                    selected = spec.scenes if group == "scene" else spec.eval_scenes
                    assert len(selected) == (f.stem not in ("same", "heldout"))
                    for c in selected:
                        instantiate(c)
                elif group in ("band", "neighbors"):
                    instantiate(cfg[group])
                elif group == "model":  # as a run builds it: KNN-DL's max_rank from the run's neighbor selector
                    instantiate(model_config_for_neighbors(cfg.model, instantiate(cfg.neighbors)))
    GlobalHydra.instance().clear()


def test_a_nerf2_folder_needs_its_band(compose_cfg, make_scene):
    folder = make_scene(n=12)
    cfg = compose_cfg("eval", ("scene=nerf2", f"scene.nerf2.path={folder}"))
    with pytest.raises(
        ConfigError,
        match=r"does not say its carrier frequency: add band=<one of 1.8ghz, 2.4ghz, "
        r"3ghz, 915mhz>",
    ):
        evaluate(cfg)

    def band_of(*overrides):
        cfg = compose_cfg("eval", overrides)
        return scene_band_config(RunSpec.of(cfg).scenes[0], cfg.get("band")).name

    assert band_of("scene=conference_v1") == "2.4ghz"  # simulated scenes: the paper's band unless band=...
    assert band_of("scene=conference_v1", "band=915mhz") == "915mhz"


def test_a_band_of_ones_own_config_folder_serves_as_a_scenes_band_and_an_eval_band(tmp_path):
    """A band file in a user's config folder (hydra.searchpath) is found wherever graf looks a band up by name (a
    scene's own ``band:``, ``eval_band``), not only as the run's ``band=``; an unknown name still lists the choices."""
    from hydra.core.hydra_config import HydraConfig

    from graf.app.config import band_choices, load_band_config

    (tmp_path / "band").mkdir()
    (tmp_path / "band" / "5.8ghz.yaml").write_text("_target_: graf.bands.Band\nname: 5.8ghz\nfrequency_hz: 5.8e9\n")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("train", [f"hydra.searchpath=[file://{tmp_path}]"], return_hydra_config=True)
        HydraConfig.instance().set_config(cfg)
        try:
            assert "5.8ghz" in band_choices() and "2.4ghz" in band_choices()
            assert instantiate(load_band_config("5.8ghz")).frequency_hz == 5.8e9
            scene = {"name": "site_a", "band": "5.8ghz"}
            assert scene_band_config(scene, None).frequency_hz == 5.8e9
            with pytest.raises(ConfigError, match=r"unknown band '6ghz': one of 1.8ghz, 2.4ghz, 3ghz, 5.8ghz, 915mhz"):
                load_band_config("6ghz")
        finally:
            HydraConfig.instance().cfg = None
    GlobalHydra.instance().clear()


def test_rfid_scene_is_915mhz_whatever_the_run_band(compose_cfg):

    for overrides in ((), ("band=2.4ghz",)):  # measured data exists at its band only (fixed_band)
        cfg = compose_cfg("eval", overrides)
        assert scene_band_config(cfg.scene.rfid_s23, cfg.get("band")).frequency_hz == 915e6


def test_eval_knn_rfid_s23_writes_results_and_predictions(compose_cfg):
    cfg = compose_cfg(
        "eval", ("model=knn", "scene=rfid_s23", "save_predictions=true", "neighbors=fixed", "neighbors.L=4")
    )
    metrics, _ = evaluate(cfg)
    out = Path(cfg.paths.output_dir)
    r = _results(cfg)
    assert RESULT_KEYS <= set(r) and set(r["metrics"]) == METRIC_KEYS
    assert (r["method"], r["scene"], r["band_hz"], r["n_train"], r["n_test"]) == ("knn", "rfid_s23", 915e6, 160, 40)
    s = r["splits"]
    assert (s["n_fit"], s["n_val"], s["val_fraction"]) == (144, 16, 0.1) and all(
        np.isfinite(list(r["metrics"].values()))
    )
    test_ids = set(int(v) for v in (CONF_DIR.parent / "embedded/rfid_s23_200/test_index.txt").read_text().split())
    assert len(s["val_ids"]) == 16 and not set(s["val_ids"]) & test_ids
    assert (out / "spectra.png").stat().st_size > 10_000
    z = np.load(out / "predictions.npz")
    assert z["pred"].shape == z["target"].shape == (40, 90, 360) and z["pred"].dtype == np.float32
    assert z["ids"].shape == (40,) and np.issubdtype(z["ids"].dtype, np.integer)
    assert 0.0 <= z["pred"].min() and z["pred"].max() <= 1.0
    # The reported PSNR and SSIM equal an independent scikit-image computation from predictions.npz.
    psnr = np.mean([peak_signal_noise_ratio(t, p, data_range=1) for p, t in zip(z["pred"], z["target"])])
    ssim = np.mean(
        [
            structural_similarity(p, t, data_range=1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
            for p, t in zip(z["pred"], z["target"])
        ]
    )
    assert abs(r["metrics"]["test/psnr"] - psnr) < 0.01
    assert abs(r["metrics"]["test/ssim"] - ssim) < 0.002
    # and the targets are the test split's spectra in the reader's order
    test_ids = [int(x) for x in (CONF_DIR.parent / "embedded/rfid_s23_200/test_index.txt").read_text().split()]
    assert z["ids"].tolist() == test_ids
    assert 20 < r["metrics"]["test/psnr"] < 40  # dense real neighbors: a sane range, not a fixed value


def test_barycentric_and_sparse_neighbors_change_the_result(compose_cfg):
    dense = evaluate(
        compose_cfg("eval", ("model.weighting=barycentric", "neighbors=fixed", "neighbors.L=6", "plot_count=0"))
    )[0]
    sparse = evaluate(
        compose_cfg(
            "eval",
            (
                "model.weighting=barycentric",
                "neighbors=fixed",
                "neighbors.L=6",
                "neighbors.exclude_within=0.25",
                "plot_count=0",
            ),
        )
    )[0]
    assert sparse["test/psnr"] < dense["test/psnr"] - 3  # s23 is dense; removing near neighbors hurts


def test_train_with_knn_skips_fit_and_tests(compose_cfg):
    cfg = compose_cfg("train", ("model=knn",))
    metrics, run = train(cfg)
    assert run.built.trainer.global_step == 0
    assert _results(cfg)["task"] == "train" and np.isfinite(metrics["test/psnr"])


def test_user_scene_folder_without_code(compose_cfg, make_scene):
    folder = make_scene(n=16, index=False)
    cfg = compose_cfg(
        "eval", ("scene=nerf2", f"scene.nerf2.path={folder}", "band=2.4ghz", "neighbors=fixed", "neighbors.L=2")
    )
    evaluate(cfg)
    r = _results(cfg)
    assert (r["n_train"], r["n_test"]) == (13, 3) and r["band_hz"] == 2.412e9
    assert "seeded split" in r["split_source"]


def test_relative_scene_path_is_found_under_data_root(compose_cfg, make_scene, tmp_path):
    folder = make_scene(n=12, name="data/mine")
    cfg = compose_cfg(
        "eval", ("scene=nerf2", "band=2.4ghz", "scene.nerf2.path=mine", f"data_root={folder.parent}", "plot_count=0")
    )
    evaluate(cfg)
    assert _results(cfg)["n_test"] == 3


def test_bad_scene_path_is_a_clear_error(compose_cfg, tmp_path):
    cfg = compose_cfg("eval", ("scene=nerf2", "band=2.4ghz", f"scene.nerf2.path={tmp_path / 'missing'}"))
    with pytest.raises(DataFormatError, match="missing: scene folder does not exist"):
        evaluate(cfg)


def test_wandb_logger_runs_offline(compose_cfg, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    cfg = compose_cfg("eval", ("logger=wandb", "plot_count=1"))
    evaluate(cfg)
    runs = list((Path(cfg.paths.output_dir) / "wandb").glob("offline-run-*"))
    assert runs and any(p.suffix == ".wandb" for p in runs[0].iterdir())


def test_csv_logger_records_test_metrics(compose_cfg):
    cfg = compose_cfg("eval", ("logger=csv", "plot_count=0"))
    evaluate(cfg)
    text = (Path(cfg.paths.output_dir) / "csv" / "metrics.csv").read_text()
    assert all(k in text for k in METRIC_KEYS)


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_table_collects_runs(compose_cfg, tmp_path):
    outs = []
    for L in (2, 4):
        cfg = compose_cfg(
            "eval",
            ("neighbors=fixed", f"neighbors.L={L}", "plot_count=0", f"paths.output_dir={tmp_path / f'runs/{L}'}"),
        )
        evaluate(cfg)
        outs.append(_results(cfg))
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        tcfg = compose(
            config_name="table", overrides=[f"runs={tmp_path / 'runs'}", f"paths.output_dir={tmp_path / 'table'}"]
        )
    GlobalHydra.instance().clear()
    payload = make_table(tcfg)
    assert [row["neighbors.L"] for row in payload["rows"]] == [2, 4]
    assert [row["PSNR"] for row in payload["rows"]] == [o["metrics"]["test/psnr"] for o in outs]
    assert "| neighbors.L |" in (tmp_path / "table" / "table.md").read_text()


def test_table_of_cross_scene_runs_has_a_row_per_test_scene_and_no_scene_config_columns():
    from graf.reports.table import build_table

    def run(trained, tested, psnrs, L):
        scenes = {n: {"name": n, "room": {"size": [i + 5.0, 4.0, 3.0]}} for i, n in enumerate(trained)}
        evals = [
            {
                "eval_scene": t,
                "n_test": 30,
                "metrics": {"test/psnr": p},
                "baselines": {"knn": {"metrics": {"test/psnr": p - 1}, "trainable_parameters": 0}},
            }
            for t, p in zip(tested, psnrs)
        ]
        return {
            "method": "graf",
            "scene": tested[0],
            "train_scenes": trained,
            "global_step": 300,
            "n_test": 30,
            "trainable_parameters": 7,
            "metrics": evals[0]["metrics"],
            "evaluations": evals,
            "config": {"scene": scenes, "eval_scene": {t: {"name": t} for t in tested}, "neighbors": {"L": L}},
        }

    header, body = build_table(
        [
            run(["room_a"], ["room_a", "room_b"], [15.0, 14.0], 4),
            run(["room_b", "room_c"], ["room_a", "room_b"], [13.0, 16.0], 8),
        ]
    )
    assert header[:4] == ["method", "trained on", "tested on", "neighbors.L"]
    assert not any(h.startswith(("scene.", "eval_scene.")) for h in header)
    rows = [dict(zip(header, r)) for r in body]
    graf = [(r["trained on"], r["tested on"], r["neighbors.L"], r["PSNR"]) for r in rows if r["method"] == "graf"]
    assert graf == [
        ("room_a", "room_a", 4, 15.0),
        ("room_a", "room_b", 4, 14.0),
        ("room_b+room_c", "room_a", 8, 13.0),
        ("room_b+room_c", "room_b", 8, 16.0),
    ]
    knn = [(r["trained on"], r["tested on"], r["PSNR"]) for r in rows if r["method"] == "knn"]
    assert knn == [("-", "room_a", 14.0), ("-", "room_b", 13.0), ("-", "room_a", 12.0), ("-", "room_b", 15.0)]


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_console_scripts_run_end_to_end(tmp_path, make_scene):
    folder = make_scene(n=12)
    bindir = Path(sys.executable).parent
    env = dict(os.environ, WANDB_MODE="offline")
    for cmd in ("graf-eval", "graf-train"):
        out = tmp_path / cmd
        proc = subprocess.run(
            [
                str(bindir / cmd),
                "scene=nerf2",
                f"scene.nerf2.path={folder}",
                "band=2.4ghz",
                "neighbors=fixed",
                "neighbors.L=2",
                "trainer.accelerator=cpu",
                f"hydra.run.dir={out}",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert "PSNR" in proc.stdout and (out / "results.json").is_file()
    proc = subprocess.run([str(bindir / "graf-eval"), "scene=nope"], capture_output=True, text=True, env=env)
    assert proc.returncode == 2 and "error: scene=nope: no such option of 'scene'" in proc.stderr


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_a_sweep_with_a_failing_job_keeps_the_table_of_the_others(tmp_path):
    exe = str(Path(sys.executable).parent / "graf-eval")
    sweep = tmp_path / "sweep"
    p = subprocess.run(
        [
            exe,
            "-m",
            "model=knn",
            "model.weighting=idw,no_such_weighting,barycentric",
            "plot_count=0",
            "logger=none",
            "data.test_subset=2",
            "trainer.enable_progress_bar=false",
            f"hydra.sweep.dir={sweep}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert p.returncode != 0  # the sweep reports the failure ...
    table = json.loads((sweep / "table.json").read_text())  # ... after running every job and tabulating them
    assert [r["method"] for r in table["rows"]] == ["knn", "knn-barycentric"]
    assert all(r["PSNR"] > 10 for r in table["rows"])
    failed = json.loads((sweep / "failed.json").read_text())
    assert [f["job"] for f in failed] == [1] and "no_such_weighting" in failed[0]["error"]
    assert "| knn-barycentric |" in (sweep / "table.md").read_text()


def test_the_comparison_study_composes_one_job_per_method_on_the_same_neighbors():
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        options = GlobalHydra.instance().config_loader().get_group_options("experiment")
        jobs = sorted(o for o in options if o.startswith("compare_rfid_s23_"))  # what glob(compare_rfid_s23_*) runs
        cfgs = {j: compose(config_name="train", overrides=[f"experiment={j}"]) for j in jobs}
    GlobalHydra.instance().clear()
    methods = {
        j: instantiate(model_config_for_neighbors(c.model, instantiate(c.neighbors))).method for j, c in cfgs.items()
    }
    assert sorted(methods.values()) == ["graf", "knn", "knn-dl", "nerf2"]
    for c in cfgs.values():
        assert c.scene.rfid_s23.name == "rfid_s23" and c.neighbors.exclude_within == 0.25 and c.baselines is None
        assert c.neighbors.L == 10 and list(c.neighbors.L_train) == [3, 10]
    steps = {methods[j]: c.trainer.max_steps for j, c in cfgs.items()}
    assert steps["graf"] == 3500 and steps["nerf2"] == 500 and steps["knn-dl"] == 2000


def test_a_glob_sweep_is_left_to_hydra_not_a_traceback():
    """``graf-train -m 'experiment=glob(compare_rfid_s23_*)'`` (the comparison page's command): graf's own check of
    the command line cannot expand a glob without Hydra's config loader, so it leaves the glob to Hydra."""
    from graf.app.overrides import check_overrides

    check_overrides("train", ["experiment=glob(compare_rfid_s23_*)", "hydra.sweep.dir=multirun/x"])
