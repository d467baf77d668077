"""The pruners a search may use (``hydra.sweeper.pruner``), made from their settings: by the sweeper that
creates the study and by the trial's pruning callback (:mod:`graf.search.pruning`), which decides with the same
pruner in the job's own process."""

from __future__ import annotations

import optuna

from graf.search.search_space import SearchSpaceError


def make_pruner(conf: dict) -> optuna.pruners.BasePruner:
    name = str(conf.get("name") or "none").lower()
    if name == "median":
        return optuna.pruners.MedianPruner(
            n_startup_trials=int(conf.get("n_startup_trials", 3)), n_warmup_steps=int(conf.get("n_warmup_steps", 0))
        )
    if name == "hyperband":
        return optuna.pruners.HyperbandPruner()
    if name == "none":
        return optuna.pruners.NopPruner()
    raise SearchSpaceError(f"hydra.sweeper.pruner.name={name}: one of median, hyperband, none")
