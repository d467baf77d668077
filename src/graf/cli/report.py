"""graf-report: the tables and figures of a study folder.

The work is :func:`graf.reports.study.report`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.reports.study import report


@graf_command("report")
def main(cfg: DictConfig) -> None:
    report(cfg)


if __name__ == "__main__":
    main()
