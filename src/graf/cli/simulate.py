"""graf-simulate: ray-trace a scene's transmitter positions at a band into a dataset file.

The work is :func:`graf.sim_commands.simulate.simulate`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.sim_commands.simulate import simulate


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="simulate")
@cli_errors
def main(cfg: DictConfig) -> None:
    simulate(cfg)


if __name__ == "__main__":
    main()
