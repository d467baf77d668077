"""The claims themselves, before any record is read: where they come from (``conf/claims.yaml``, or the user's own
file: :func:`claims_file`, :func:`read_claims`) and what each must hold (:func:`check_claims`).  A user's file that
cannot be read, a claim lacking what its kind reads, and a ``records`` folder that does not exist are refused in one
line naming the file, the claim or the folder.
"""

from __future__ import annotations

from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from graf.app.config import CONF_DIR, override_key
from graf.errors import ConfigError
from graf.plugins import one_line

# what each kind reads from its claim (besides id and kind): a claim lacking one is refused, not a KeyError
NEEDS = {
    "paired": ("record", "method", "reference", "metric"),
    "value": ("record", "key", "paper_value"),
    "difference": ("record", "key", "paper_value"),
    "change": ("record", "method", "L_from", "L_to", "metric"),
    "transfer": ("record", "method", "metric"),
    "note": ("reason",),
    "distance": ("record", "method", "reference", "metric"),  # a finding beyond the paper
}


def check_claim(claim, where: str = "claims", number: int | None = None) -> None:
    """Refuse, in one line naming ``where`` (the claims file) and the claim, a claim the ledger cannot read: not a
    mapping, no id, a kind it does not know, or a setting its kind reads left out."""
    which = f"claim {number}" if number is not None else "a claim"
    if not isinstance(claim, dict):
        raise ConfigError(f"{where}: {which} is not a mapping of settings (id, kind, record, ...): {claim!r}")
    if claim.get("id") in (None, ""):
        raise ConfigError(f"{where}: {which} has no id")
    kind = claim.get("kind")
    if kind not in NEEDS:
        raise ConfigError(f"{where}: claim {claim['id']!r}: kind must be one of {list(NEEDS)}, got {kind!r}")
    missing = [k for k in NEEDS[kind] if claim.get(k) in (None, "")]
    if kind == "change" and claim.get("tolerance") is None and claim.get("paper_value") is None:
        missing.append("paper_value (or tolerance)")
    if missing:
        raise ConfigError(f"{where}: claim {claim['id']!r} (kind {kind}) lacks {', '.join(missing)}")


def check_claims(claims, where: str = "claims") -> None:
    """Refuse, in one line naming ``where``, claims the ledger cannot read: not a list, a claim
    :func:`check_claim` refuses, or an id used twice."""
    if not isinstance(claims, list) or not claims:
        raise ConfigError(f"{where}: claims must be a non-empty list (each claim with id, kind, ...), got {claims!r}")
    for number, claim in enumerate(claims, 1):
        check_claim(claim, where, number)
    ids = [c["id"] for c in claims]
    dup = sorted({str(i) for i in ids if ids.count(i) > 1})
    if dup:
        raise ConfigError(f"{where}: claim ids used twice: {dup}")
    bases = {c["id"] for c in claims if not c.get("of")}
    for c in claims:
        if c.get("of") and (c["of"] not in bases or ids.index(c["of"]) > ids.index(c["id"])):
            raise ConfigError(
                f"{where}: claim {c['id']!r}: of={c['of']!r} must name an earlier claim that is not itself a re-run"
            )


def claims_file(cfg: DictConfig) -> Path | None:
    """The user's own claims file, or None for ``conf/claims.yaml``: ``claims=<file>`` (a path given for the
    setting), else a ``claims.yaml`` in a config folder of the user's (``--config-dir``, ``hydra.searchpath``) of a
    run of graf-claims' own config: Hydra finds graf's file of that name first and would silently use it instead."""
    given = cfg.get("claims")
    if isinstance(given, str):
        return Path(given)
    if not HydraConfig.initialized() or HydraConfig.get().job.config_name != "claims":
        return None
    for source in HydraConfig.get().runtime.config_sources:
        folder = Path(source.path)
        if source.schema == "file" and folder.resolve() != CONF_DIR.resolve() and (folder / "claims.yaml").is_file():
            return folder / "claims.yaml"
    return None


def read_claims(cfg: DictConfig) -> tuple[DictConfig, list[dict], str]:
    """``(cfg, claims, where)``: the run's config and its claims, from :func:`claims_file` when the user gave one
    (its settings beside ``claims``, such as ``records`` and ``method``, apply unless the command line sets them),
    else from ``cfg.claims``; ``where`` names their file.  A file that cannot be read as YAML, or holds no list of
    claims, is refused in one line naming it; its claims are then checked (:func:`check_claims`)."""
    path = claims_file(cfg)
    where = "claims" if path is None else str(path)
    if path is not None:
        if not path.is_file():
            raise ConfigError(f"claims={path}: no such claims file")
        try:
            node = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        except Exception as exc:  # noqa: BLE001 - the YAML parser's or OmegaConf's own, said with the file
            raise ConfigError(f"{path}: not a readable claims file ({one_line(exc)})") from None
        node = {"claims": node} if isinstance(node, list) else node
        if not isinstance(node, dict) or not isinstance(node.get("claims"), list):
            raise ConfigError(f"{path}: holds no list of claims (a 'claims:' list, each claim with id, kind, ...)")
        given = {override_key(o) for o in HydraConfig.get().overrides.task} if HydraConfig.initialized() else set()
        cfg = cfg.copy()
        with open_dict(cfg):
            for key, value in node.items():
                if key == "claims" or (key not in ("defaults", "hydra") and key not in given):
                    cfg[key] = value
    try:
        claims = OmegaConf.to_container(cfg.claims, resolve=True) if isinstance(cfg.claims, ListConfig) else cfg.claims
    except Exception as exc:  # noqa: BLE001 - an interpolation the file's claims make that does not resolve
        raise ConfigError(f"{where}: {one_line(exc)}") from None
    check_claims(claims, where)
    return cfg, claims, where


def check_records(root: Path) -> None:
    """Refuse a ``records`` folder that does not exist: every claim would be "not reproduced" for want of it."""
    if not root.is_dir():
        what = "is a file, not a folder" if root.exists() else "no such folder"
        raise ConfigError(f"records={root}: {what} (the folder the claims' record paths are relative to)")
