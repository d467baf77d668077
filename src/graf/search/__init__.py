"""Hyperparameter searches: the objectives a search may optimise (validation data only), the Optuna
sweeper's machinery (:mod:`graf.search.optuna_sweeper`, plugged into Hydra by
``hydra_plugins.graf_optuna_sweeper``), pruning during training, and the study's output files."""
