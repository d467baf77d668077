"""graf-oracle: the per-pixel linear-fusion oracle of supplement A.2 on a scene (see graf.case_studies.oracle).

The work is :func:`graf.case_studies.oracle.run`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.case_studies.oracle import run
from graf.cli.entry import graf_command


@graf_command("oracle")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
