"""graf-bench-sim: how fast the simulator makes spectra here, and whether its sample budget converged.

The work is :func:`graf.sim.benchmark.bench`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.sim.benchmark import bench


@graf_command("bench_sim")
def main(cfg: DictConfig) -> None:
    bench(cfg)


if __name__ == "__main__":
    main()
