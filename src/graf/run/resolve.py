"""A run resolved once: the config a graf-train job runs, read into one :class:`~graf.app.spec.RunSpec`.

Resolving applies, in this order, to a config whose study budget is already filled in
(:func:`graf.run.budgets.with_study_budget`, which graf-train applies first: a finished job is recognised by it): the
command line's ``baselines={}``, the fine-tuning base's folder and checkpoint, ``eval_scene=heldout``'s layouts, and
the fine-tuning steps and learning rate; then the settings are checked, before anything is built, trained or moved.
The run functions read the spec it returns, not the config's groups.
"""

from __future__ import annotations

from omegaconf import DictConfig

from graf.app.config import check_run_settings, with_baselines_switch
from graf.app.spec import RunSpec, expand_heldout
from graf.errors import ConfigError
from graf.run.finetune import check_finetune, finetune_config, resolve_base


def resolve_run(cfg: DictConfig) -> RunSpec:
    """The spec of the run ``cfg`` composes (its study budget filled in), resolved and checked (one clear error for a
    bad setting)."""
    cfg = expand_heldout(resolve_base(with_baselines_switch(cfg)))
    check_run_settings(cfg)
    check_finetune(cfg)
    if (cfg.get("finetune") or {}).get("init_from"):
        cfg = finetune_config(cfg)
    check_training_length(cfg)
    return RunSpec.of(cfg)


def check_training_length(cfg: DictConfig) -> None:
    """``trainer.max_steps`` governs training; epochs are unbounded unless ``trainer.max_epochs`` is set (a limit
    of the user's own).  Refuse settings that are not counts, or that would never end."""
    t = cfg.get("trainer") or {}
    for key in ("max_steps", "max_epochs"):
        v = t.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < -1):
            raise ConfigError(f"trainer.{key} must be an integer >= -1 (-1: no limit), got {v!r}")
    if t.get("max_steps", -1) in (None, -1) and t.get("max_epochs", -1) in (None, -1):
        raise ConfigError(
            "trainer.max_steps=-1 and trainer.max_epochs=-1: training would never end; set "
            "trainer.max_steps=N (optimiser steps)"
        )
