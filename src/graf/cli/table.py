"""graf-table: collect results.json files (a run, a multirun folder, or several) into one table.

The work is :func:`graf.reports.table.make_table`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.reports.table import make_table


@graf_command("table")
def main(cfg: DictConfig) -> None:
    make_table(cfg)


if __name__ == "__main__":
    main()
