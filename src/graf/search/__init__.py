"""What a run of a hyperparameter search needs: the objectives a search may optimise (validation data only), the
search space, pruning during training and the pruners.  The Optuna sweeper that drives the runs is above them,
in :mod:`graf.sweeper`."""
