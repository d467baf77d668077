"""graf-report: the tables and figures of a study folder.

The work is :func:`graf.studies.report.report`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cli.entry import CONF_PATH, cli_errors
from graf.studies.report import report


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="report")
@cli_errors
def main(cfg: DictConfig) -> None:
    report(cfg)


if __name__ == "__main__":
    main()
