"""graf-curves: learning curves on validation data (``conf/curves.yaml``).

The work is :func:`graf.studies.curves.curves`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.studies.curves import curves


@graf_command("curves")
def main(cfg: DictConfig) -> None:
    curves(cfg)


if __name__ == "__main__":
    main()
