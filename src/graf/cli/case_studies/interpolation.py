"""graf-interp: the interpolation theorem measured on a scene's field (error against dP, the quadratic regime,
the curvature K).  The work is :func:`graf.case_studies.interpolation.run`, callable from Python with a composed
config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.case_studies.interpolation import run
from graf.cli.entry import graf_command


@graf_command("interp")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
