"""graf-synthesize: spectra at new transmitter positions from a checkpoint, as a NeRF2-format folder.

The work is :func:`graf.case_studies.synthesis.run`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.case_studies.synthesis import run
from graf.cli.entry import graf_command


@graf_command("synthesize")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
