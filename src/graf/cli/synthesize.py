"""graf-synthesize: spectra at new transmitter positions from a checkpoint, as a NeRF2-format folder.

The work is :func:`graf.cases.synthesis.run`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cases.synthesis import run
from graf.cli.entry import CONF_PATH, cli_errors


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="synthesize")
@cli_errors
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
