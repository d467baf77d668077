"""graf-localize: a localization model trained from random initialisation and pre-trained on each method's
synthesized spectra, against the number of measured spectra.  The work is :func:`graf.case_studies.localization.run`."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.case_studies.localization import run
from graf.cli.entry import graf_command


@graf_command("localize")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
