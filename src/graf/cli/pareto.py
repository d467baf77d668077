"""graf-pareto: GRaF's speed/accuracy trade, measured (the knobs of ``conf/pareto.yaml``).

The work is :func:`graf.studies.pareto.sweep`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.studies.pareto import sweep


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="pareto")
@cli_errors
def main(cfg: DictConfig) -> None:
    sweep(cfg)


if __name__ == "__main__":
    main()
