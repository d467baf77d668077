"""graf-train: fit the model when it has parameters, then test it beside its baselines; writes results.json.

The work is :func:`graf.run.train.train`; the value returned to a sweeper is the run's objective
(:func:`graf.run.evaluation.sweep_value`: validation figures and costs only).
"""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.run.evaluation import sweep_value
from graf.run.train import train


@graf_command("train")
def main(cfg: DictConfig) -> float:
    metrics, run = train(cfg)
    return sweep_value(cfg, metrics, run)


if __name__ == "__main__":
    main()
