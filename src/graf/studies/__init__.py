"""Tools over many runs: tables (graf-table), study reports (graf-report), learning curves (graf-curves),
Pareto fronts (graf-pareto) and the model benchmark (graf-bench)."""
