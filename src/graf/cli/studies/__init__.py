"""Commands over many runs: graf-curves, graf-pareto, graf-bench."""
