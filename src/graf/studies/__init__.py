"""Tools that run many runs, each a command in a subprocess (:func:`graf.app.launch.command`): learning curves
(graf-curves), Pareto fronts (graf-pareto) and the model benchmark (graf-bench).  The reports over their records
are in :mod:`graf.reports`."""
