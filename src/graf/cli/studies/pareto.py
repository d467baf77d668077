"""graf-pareto: GRaF's speed/accuracy trade, measured (the knobs of ``conf/pareto.yaml``).

The work is :func:`graf.studies.pareto.sweep`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.studies.pareto import sweep


@graf_command("pareto")
def main(cfg: DictConfig) -> None:
    sweep(cfg)


if __name__ == "__main__":
    main()
