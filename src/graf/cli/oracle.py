"""graf-oracle: the per-pixel linear-fusion oracle of seed appendix A.2 on a scene (see graf.analysis.oracle).

The work is :func:`graf.cases.oracle.run`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cases.oracle import run
from graf.cli.entry import CONF_PATH, cli_errors


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="oracle")
@cli_errors
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
