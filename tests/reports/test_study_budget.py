"""Each trained model's study budget at the paper's density: the step its learning curve chose (``study_budgets``
in ``study_size=paper``), applied to a study job whose ``study_steps`` is left null; a ``study_steps`` set anywhere
(command line or config file) wins."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from graf.app.config import CONF_DIR
from graf.errors import ConfigError
from graf.reports.choices import best_step, choose, still_gaining
from graf.run.budgets import study_budget, with_study_budget
from graf.run.train import warn_other_length

ROOT = Path(__file__).resolve().parents[2]
CURVES = ROOT / "sweeps" / "learning_curves" / "curves.csv"
MODE_PRESETS = {"ray_weights": "graf_cpu_scenes_ray_weights", "ray_knn": "graf_cpu_scenes_ray_knn"}


def _job_config(*overrides: str, conf: Path | None = None):
    """A study job's config as Hydra hands it to the task (HydraConfig set, as in a running multirun job); ``conf``:
    a user's config folder on the search path."""
    extra = [f"hydra.searchpath=[file://{conf}]"] if conf else []
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", overrides=[*overrides, *extra], return_hydra_config=True)
        HydraConfig.instance().set_config(cfg)
        out = with_study_budget(cfg)
        steps = out.trainer.max_steps
    GlobalHydra.instance().clear()
    return out, steps


def test_a_listed_model_gets_its_budget_and_any_other_the_default():
    budgets = {"graf_cpu_scenes_ray_weights": 3000, "knn_dl": 300}
    assert study_budget(budgets, "graf_cpu_scenes_ray_weights", 300) == 3000
    assert study_budget(budgets, "knn_dl", 300) == 300
    assert study_budget(budgets, "nerf2_study", 250) == 250  # no budget of its own: study_budget_default
    assert study_budget({}, "knn_dl", 250) == 250
    for bad in (0, -5, 2.5, "300", True, None):
        with pytest.raises(ConfigError, match="study_budgets.knn_dl"):
            study_budget({"knn_dl": bad}, "knn_dl", 300)
        with pytest.raises(ConfigError, match="study_budget_default"):
            study_budget(budgets, "nerf2_study", bad)


def test_a_paper_density_study_job_trains_its_model_s_budget():
    paper = OmegaConf.load(CONF_DIR / "study_size" / "paper.yaml").study_budgets
    _, steps = _job_config("experiment=cross_scene_matrix")  # the studies' GRaF, the default model
    assert steps == paper.graf_cpu_scenes_ray_weights
    _, steps = _job_config("experiment=cross_scene_matrix", "model=knn_dl", "study_budget_default=7")
    assert steps == paper.knn_dl
    _, steps = _job_config("experiment=cross_scene_matrix", "model=nerf2_study", "study_budget_default=7")
    assert steps == 7  # no budget of its own: the default
    cfg, steps = _job_config("experiment=neighbor_count", "study_steps=7")
    assert steps == 7 and cfg.study_steps == 7
    _, steps = _job_config("experiment=cross_scene_matrix", "study_size=quick")  # the smoke size has no budgets
    assert steps == 300
    _, steps = _job_config("experiment=cross_scene_matrix", "study_size=quick", "study_steps=9")
    assert steps == 9


def test_a_study_steps_set_in_a_config_file_wins_over_the_budget(tmp_path):
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "my_matrix.yaml").write_text(
        "# @package _global_\ndefaults:\n  - cross_scene_matrix\n  - _self_\nstudy_steps: 500\n"
    )
    cfg, steps = _job_config("experiment=my_matrix", conf=tmp_path)
    assert cfg.study_budgets.graf_cpu_scenes_ray_weights == 1000  # the budget is there, and the file's value wins
    assert steps == 500 and cfg.study_steps == 500
    _, steps = _job_config("experiment=my_matrix", "model=knn_dl", conf=tmp_path)
    assert steps == 500


def test_the_budgets_are_the_published_paper_density_curves_choice():
    """study_budgets holds the preset of the GRaF mode chosen on regime cross_family_val (validated on layouts no
    study tests on), and each budget is what the rule gives on regime matrix_recipe_val (the matrix job's own recipe,
    on the same validation layouts): the smallest step within BUDGET_WITHIN_DB of the best validation PSNR."""
    from graf.run.budgets import BUDGET_WITHIN_DB

    rows = list(csv.DictReader(CURVES.open()))
    mode, _ = choose(
        [r for r in rows if r["regime"] == "cross_family_val"], ["pooled", "ray", "ray_knn", "ray_weights"]
    )
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        budgets = compose("train", overrides=["experiment=cross_scene_matrix"]).study_budgets
    GlobalHydra.instance().clear()
    budgets = dict(budgets)
    per_scene = budgets.pop("rf_gs")  # a per-scene method: its own curve (regime paper_within), tested below
    assert isinstance(per_scene, int) and per_scene >= 1
    recipe = [r for r in rows if r["regime"] == "matrix_recipe_val"]
    assert budgets == {
        MODE_PRESETS[mode]: best_step(recipe, mode, within_db=BUDGET_WITHIN_DB),
        "knn_dl": best_step(recipe, "knn_dl", within_db=BUDGET_WITHIN_DB),
    }
    assert (CONF_DIR / "model" / f"{MODE_PRESETS[mode]}.yaml").is_file()


def test_best_step_takes_the_smaller_step_on_a_tie_and_none_without_points():
    rows = [
        {"regime": "r", "method": "m", "step": "100", "val_psnr": "20.0"},
        {"regime": "r", "method": "m", "step": "300", "val_psnr": "21.5"},
        {"regime": "r", "method": "m", "step": "1000", "val_psnr": "21.5"},
        {"regime": "q", "method": "m", "step": "3000", "val_psnr": "30.0"},
        {"regime": "r", "method": "m", "step": "3000", "val_psnr": ""},
    ]
    assert best_step(rows, "m", "r") == 300
    assert best_step(rows, "m") == 3000
    assert best_step(rows, "other") is None


def test_the_budget_within_a_tolerance_is_the_smallest_step_near_the_best():
    rows = [
        {"regime": "r", "method": "m", "step": str(s), "val_psnr": str(p)}
        for s, p in [(1000, 20.0), (3000, 21.45), (10000, 21.5)]
    ]
    assert best_step(rows, "m", "r") == 10000
    assert best_step(rows, "m", "r", within_db=0.1) == 3000  # 21.45 >= 21.5 - 0.1
    assert best_step(rows, "m", "r", within_db=0.01) == 10000


def test_a_curve_still_gaining_per_doubling_is_extended():
    pts = [(3000, 21.0), (10000, 21.2)]  # 0.2 dB over log2(10/3) = 1.74 doublings: 0.115 per doubling
    rows = [{"regime": "r", "method": "m", "step": str(s), "val_psnr": str(p)} for s, p in pts]
    assert still_gaining(rows, "m", "r") is True
    assert still_gaining(rows, "m", "r", per_doubling_db=0.12) is False
    assert still_gaining(rows[:1], "m", "r") is None


def test_a_finished_job_of_another_length_is_kept_with_a_warning(tmp_path, caplog):
    cfg = OmegaConf.create({"trainer": {"max_steps": 3000}, "finetune": {"init_from": None}})
    with caplog.at_level(logging.WARNING, logger="graf"):
        warn_other_length(cfg, tmp_path, {"training": {"max_steps": 300}})
    assert "trained 300 steps" in caplog.text and "train 3000 now" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="graf"):
        warn_other_length(cfg, tmp_path, {"training": {"max_steps": 3000}})  # the same length
        warn_other_length(cfg, tmp_path, {"training": None})  # a zero-shot job trained nothing
        ft = OmegaConf.create({"trainer": {"max_steps": 3000}, "finetune": {"init_from": "base.ckpt"}})
        warn_other_length(ft, tmp_path, {"training": {"max_steps": 50}})  # fine-tuning sets its steps later
    assert caplog.text == ""


def test_every_study_budget_is_the_step_its_curve_s_rule_gives():
    """Each budget of ``study_size=paper`` names its curve (``study_budget_curves``), and is the step the studies' rule
    reads off it (the smallest step within BUDGET_WITHIN_DB of the curve's best validation PSNR) in the published
    curves: a budget typed into the config that its curve does not give fails here."""
    from graf.run.budgets import BUDGET_WITHIN_DB

    paper = OmegaConf.load(CONF_DIR / "study_size" / "paper.yaml")
    rows = list(csv.DictReader(CURVES.open()))
    assert set(paper.study_budgets) == set(paper.study_budget_curves)  # no budget without its curve
    for model, budget in paper.study_budgets.items():
        where = paper.study_budget_curves[model]
        step = best_step(rows, where.curve, where.regime, BUDGET_WITHIN_DB)
        assert step is not None, f"{model}: no curve {where.curve} in regime {where.regime} of {CURVES}"
        assert budget == step, (
            f"study_budgets.{model} = {budget}, but its curve ({where.regime}, {where.curve}) gives {step}"
        )
