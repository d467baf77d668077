"""graf-curves' settings (``conf/curves.yaml`` and the command line), checked before any run: one line naming the
first wrong one (:class:`graf.errors.ConfigError`), never a cast (``until=2.5`` is no 2) nor a traceback."""

from __future__ import annotations

from omegaconf import DictConfig, ListConfig

from graf.app.config import check_int
from graf.errors import ConfigError, as_override
from graf.reports.choices import continued_regimes


def subset(items, keep, what: str) -> dict:
    """The entries of ``items`` whose keys the list ``keep`` names (None: all); ``what`` names the setting."""
    if keep is None:
        return dict(items)
    if not isinstance(keep, (list, ListConfig)):  # only_regimes=rfid_sparse was read letter by letter
        raise ConfigError(f"{what}={as_override(keep)}: must be a list, such as [{keep}]")
    unknown = set(keep) - set(items)
    if unknown:
        raise ConfigError(f"{what}: unknown keys {sorted(unknown)} (known: {sorted(items)})")
    return {k: v for k, v in items.items() if k in set(keep)}


EACH_POINT = ("resume", "own_run")  # a regime's each_point: how its points are trained (conf/curves.yaml)


def own_runs(regime: DictConfig, rname: str) -> bool:
    """Whether the regime's points are runs of their own (``each_point: own_run``: each trains from scratch with a
    schedule over its own steps, the recipe a study of that budget runs) rather than one trajectory resumed from
    point to point with the schedule over the regime's budget (``resume``, the default)."""
    mode = str(regime.get("each_point") or "resume")
    if mode not in EACH_POINT:
        raise ConfigError(f"curves.yaml: regimes.{rname}.each_point: {mode!r} is not one of {', '.join(EACH_POINT)}")
    return mode == "own_run"


def check_settings(cfg: DictConfig) -> None:
    """``until`` (null or a positive int: -1 ran nothing and said nothing), ``threads``, ``checkpoint_every`` (0 would
    switch the periodic saves, and the curve's resume chain, off), every ``steps`` list (``steps=abc`` was read
    letter by letter) and budget, each regime's ``each_point``, ``only_regimes`` and ``only_methods``, and that a
    regime's ``continues`` names another regime (the site's check,
    :func:`graf.reports.choices.continued_regimes`)."""
    check_int(cfg.get("until"), "until", none=True)
    check_int(cfg.get("threads"), "threads", none=True)
    check_int(cfg.checkpoint_every, "checkpoint_every")
    lists = [("steps", cfg.steps)] + [(f"regimes.{n}.steps", r.steps) for n, r in cfg.regimes.items() if r.get("steps")]
    for key, steps in lists:
        if not isinstance(steps, (list, ListConfig)):
            raise ConfigError(f"{key}={as_override(steps)}: must be a list of step counts, such as [100,1000]")
        for i, s in enumerate(steps):
            check_int(s, f"{key}[{i}]")
    for name, regime in cfg.regimes.items():
        check_int(regime.max_steps, f"regimes.{name}.max_steps")
        own_runs(regime, name)  # each_point: resume or own_run
    subset(cfg.regimes, cfg.get("only_regimes"), "only_regimes")
    subset(cfg.methods, cfg.get("only_methods"), "only_methods")
    continued_regimes(cfg.regimes, "curves.yaml")
