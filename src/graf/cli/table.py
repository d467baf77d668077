"""graf-table: collect results.json files (a run, a multirun folder, or several) into one table.

The work is :func:`graf.studies.table.make_table`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.studies.table import make_table


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="table")
@cli_errors
def main(cfg: DictConfig) -> None:
    make_table(cfg)


if __name__ == "__main__":
    main()
