"""What a run of a search needs (graf.search): the search space's grammar, the objectives (never a test metric;
each one's direction from the metric registry), the means over the evaluated scenes, and pruning."""

from __future__ import annotations

import optuna
import pytest

from graf.search.objectives import check_objective_names, objective_values


def test_the_validation_that_ends_training_never_prunes():
    from types import SimpleNamespace

    import torch

    from graf.search.pruning import OptunaPruning

    study = optuna.create_study(
        direction="maximize", pruner=optuna.pruners.MedianPruner(n_startup_trials=1, n_warmup_steps=0)
    )
    done = study.ask()
    done.report(10.0, 2)
    done.report(10.0, 4)
    study.tell(done, 10.0)

    def trainer(step):
        return SimpleNamespace(
            sanity_checking=False,
            global_step=step,
            max_steps=4,
            callback_metrics={"val/psnr": torch.tensor(-10.0)},
            is_global_zero=True,
            world_size=1,
        )

    last = OptunaPruning(study.ask(), "val/psnr")
    last.on_validation_end(trainer(4), None)  # far under the median, but training is over: reported, not pruned
    assert last.reported == [(4, -10.0)]
    early = OptunaPruning(study.ask(), "val/psnr")
    with pytest.raises(optuna.TrialPruned):
        early.on_validation_end(trainer(2), None)


def test_search_space_grammar():
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    from graf.search.search_space import SearchSpaceError, parse_search_space

    parser = OverridesParser.create()
    space = parse_search_space(
        {
            "a": "interval(0, 1)",
            "b": "tag(log, interval(1e-4, 1e-2))",
            "c": "range(2, 5)",
            "d": "choice([1,2],[3,10])",
            "e": "tag(int, interval(1, 9))",
            "f": "choice(1,2)",
        },
        ["g=3", "f=choice(4,5,6)"],
        parser,
    )
    d = space.distributions
    assert d["a"] == FloatDistribution(0.0, 1.0)
    assert d["b"] == FloatDistribution(1e-4, 1e-2, log=True)
    assert d["c"] == IntDistribution(2, 5)  # upper bound included
    assert d["d"] == CategoricalDistribution(["[1,2]", "[3,10]"])
    assert d["e"] == IntDistribution(1, 9)
    assert d["f"] == CategoricalDistribution(["4", "5", "6"])  # the command line wins over params
    assert space.fixed == ["g=3"]
    assert space.overrides({"d": "[3,10]", "b": 0.001}) == ["g=3", "d=[3,10]", "b=0.001"]
    with pytest.raises(SearchSpaceError, match="log"):
        parse_search_space({"b": "tag(log, interval(0, 1))"}, [], parser)


def test_objectives_refuse_test_metrics_and_average_over_test_scenes():
    from graf.errors import ConfigError

    for bad in ("test/psnr", "test/psnr@mean", "val/psnr@max", "cost/train_s"):
        with pytest.raises(ConfigError, match="test split"):
            check_objective_names([bad])
    metrics = {"val/psnr": 20.0, "test/psnr": 99.0}
    per_scene = [{"val/psnr": 20.0, "test/psnr": 99.0}, {"val/psnr": 10.0, "test/psnr": 98.0}]
    assert objective_values(["val/psnr", "val/psnr@mean"], metrics, per_scene) == [20.0, 15.0]


def test_best_json_means_are_the_means_over_the_evaluated_scenes():
    from graf.search.objectives import metrics_mean

    evals = [
        {"eval_scene": "a", "metrics": {"val/psnr": 15.0, "test/psnr": 14.0, "val/ssim": 0.5}},
        {"eval_scene": "b", "metrics": {"val/psnr": 13.0, "test/psnr": 16.0}},
    ]
    assert metrics_mean(evals) == {"val/psnr": 14.0, "test/psnr": 15.0}  # only metrics every scene has
    assert metrics_mean(evals[:1]) is None and metrics_mean([]) is None


def test_directions_are_the_metrics_own_and_a_given_one_is_checked():
    from graf.errors import ConfigError
    from graf.search.objectives import objective_directions

    names = ["val/psnr@mean", "cost/infer_s_per_spectrum", "val/lpips"]
    assert objective_directions(names) == ["maximize", "minimize", "minimize"]
    assert objective_directions(["val/ssim", "val/mse"], ["maximize", "minimize"]) == ["maximize", "minimize"]
    assert objective_directions(["val/psnr"], "maximize") == ["maximize"]
    with pytest.raises(ConfigError, match="one direction per objective"):
        objective_directions(["val/psnr", "val/ssim"], "maximize")
    with pytest.raises(ConfigError, match="not maximize or minimize"):
        objective_directions(["val/psnr"], "up")
    with pytest.raises(ConfigError, match=r"contradicts the metric \(lower is better"):
        objective_directions(["val/mse"], ["maximize"])
