"""graf-curves: learning curves on validation data (``conf/curves.yaml``).

The work is :func:`graf.studies.curves.curves`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.studies.curves import curves


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="curves")
@cli_errors
def main(cfg: DictConfig) -> None:
    curves(cfg)


if __name__ == "__main__":
    main()
