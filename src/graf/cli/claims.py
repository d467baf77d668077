"""graf-claims: the ledger of the paper's claims against the platform's records.

The work is :func:`graf.reports.claims.claims`, callable from Python with a composed config."""

from __future__ import annotations

from omegaconf import DictConfig

from graf.cli.entry import graf_command
from graf.reports.claims import claims


@graf_command("claims")
def main(cfg: DictConfig) -> None:
    claims(cfg)


if __name__ == "__main__":
    main()
