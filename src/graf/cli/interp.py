"""graf-interp: the interpolation theorem measured on a scene's field (error against dP, the quadratic regime,
the curvature K).  The work is :func:`graf.cases.interp.run`, callable from Python with a composed config."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from graf.cases.interp import run
from graf.cli.entry import CONF_PATH, cli_errors


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="interp")
@cli_errors
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
