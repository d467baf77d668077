"""The studies' training budgets: the rule that chooses them on a learning curve, and each study job's budget.

A study job (an ``experiment`` of ``conf/experiment/base/study.yaml``) leaves ``study_steps`` null; the budget of its
``model=`` preset is then its entry in the study size's ``study_budgets`` (``conf/study_size/paper.yaml``), read off
that model's learning curve by :data:`BUDGET_WITHIN_DB`'s rule (:func:`graf.reports.choices.best_step` applies
it; ``tests/reports/test_study_budget.py`` fails when a budget there disagrees with its curve), else
``study_budget_default``.
"""

from __future__ import annotations

import logging

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

from graf.errors import ConfigError

log = logging.getLogger("graf")

# The studies' budget rule, fixed before the curves were run: a method's budget is the smallest step whose validation
# PSNR lies within this many dB of its curve's best.
BUDGET_WITHIN_DB = 0.1


def study_budget(budgets, model: str | None, default) -> int:
    """The training steps a study gives ``model`` (a ``model=`` preset name) when its ``study_steps`` is left
    null: its entry in ``budgets`` (the study size's ``study_budgets``: each method's budget chosen on its learning
    curve), else ``default`` (``study_budget_default``)."""
    key = f"study_budgets.{model}" if budgets and model in budgets else "study_budget_default"
    steps = budgets[model] if key != "study_budget_default" else default
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ConfigError(f"{key}={steps!r}: a budget is a positive whole number of training steps")
    return steps


def with_study_budget(cfg: DictConfig) -> DictConfig:
    """A study job's config with ``study_steps`` (and so ``trainer.max_steps``) filled in when it is null: the
    model's budget (:func:`study_budget`), with one log line saying which.  A ``study_steps`` set anywhere (command
    line or config file) is every model's budget."""
    if "study_steps" not in cfg:
        return cfg
    model = HydraConfig.get().runtime.choices.get("model") if HydraConfig.initialized() else None
    if cfg.study_steps is not None:
        log.info("model=%s trains study_steps=%s (set in the config or on the command line)", model, cfg.study_steps)
        return cfg
    budgets = cfg.get("study_budgets") or {}
    steps = study_budget(budgets, model, cfg.get("study_budget_default"))
    why = "its study budget (study_budgets)" if model in budgets else "study_budget_default: no budget of its own"
    log.info("model=%s trains %d steps, %s; study_steps=N sets another", model, steps, why)
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.study_steps = steps
    return cfg
