"""graf-show-scenes: a picture of a few spectra from each simulated scene's dataset at one band.

The work is :func:`graf.sim_commands.show_scenes.show`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.sim_commands.show_scenes import show


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="show_scenes")
@cli_errors
def main(cfg: DictConfig) -> None:
    show(cfg)


if __name__ == "__main__":
    main()
