"""graf-bench: the methods' cost side by side on a real and a simulated scene.

The work is :func:`graf.studies.bench.bench`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.studies.bench import bench


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="bench")
@cli_errors
def main(cfg: DictConfig) -> None:
    bench(cfg)


if __name__ == "__main__":
    main()
