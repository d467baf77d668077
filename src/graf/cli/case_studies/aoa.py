"""graf-aoa: the angle of arrival of the direct path from each method's predicted spectra, against the geometry
and the true spectra.  The work is :func:`graf.case_studies.aoa.run`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.case_studies.aoa import run
from graf.cli.entry import graf_command


@graf_command("aoa")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
