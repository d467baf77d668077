"""graf-bench-sim: how fast the simulator makes spectra here, and whether its sample budget converged.

The work is :func:`graf.sim_commands.bench.bench`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.sim_commands.bench import bench


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="bench_sim")
@cli_errors
def main(cfg: DictConfig) -> None:
    bench(cfg)


if __name__ == "__main__":
    main()
