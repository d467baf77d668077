"""graf-simulate: ray-trace a scene's transmitter positions at a band into a dataset file.

The work is :func:`graf.sim.simulate.simulate`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.sim.simulate import simulate


@graf_command("simulate")
def main(cfg: DictConfig) -> None:
    simulate(cfg)


if __name__ == "__main__":
    main()
