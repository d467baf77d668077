"""The Optuna sweeper that drives runs (``hydra/sweeper=graf_optuna``, registered by
``hydra_plugins.graf_optuna_sweeper``): trials, their storage and the study's output files; above the run it drives."""
