"""graf-bench: the methods' cost side by side on a real and a simulated scene.

The work is :func:`graf.studies.bench.bench`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.studies.bench import bench


@graf_command("bench")
def main(cfg: DictConfig) -> None:
    bench(cfg)


if __name__ == "__main__":
    main()
