"""graf-show-scenes: a picture of a few spectra from each simulated scene's dataset at one band.

The work is :func:`graf.sim.show.show`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.sim.show import show


@graf_command("show_scenes")
def main(cfg: DictConfig) -> None:
    show(cfg)


if __name__ == "__main__":
    main()
