"""Learning-rate schedules whose length follows the run: GRaF's and KNN-DL's exponential decay
(``decay_steps``) and NeRF2's cosine (``t_max``) default to the trainer's ``max_steps`` (null in the presets),
so a 300-step run decays over 300 steps, not over the paper's 300,000 at a nearly constant rate.  A length set
explicitly is kept; one more than :data:`LONG` times the run's steps is warned about in one line.  Each module
keeps what ran in ``schedule_record`` (``results.json`` ``schedule``: kind, steps, start and end learning rate).
Every method's constructor refuses a learning rate that is not finite and positive (:func:`check_rates`).
"""

from __future__ import annotations

import logging
import math

log = logging.getLogger("graf")
LONG = 10  # a schedule longer than LONG x the run's steps is warned about


def run_steps(module) -> int | None:
    """The optimiser steps the run will take: the trainer's ``max_steps``, else its estimate (epochs x batches);
    None outside a fit (no trainer attached)."""
    trainer = getattr(module, "_trainer", None)
    if trainer is None:
        return None
    if trainer.max_steps and trainer.max_steps > 0:
        return int(trainer.max_steps)
    try:
        est = trainer.estimated_stepping_batches
    except Exception:  # no datamodule attached (a bare optimiser set-up)
        return None
    return int(est) if est and math.isfinite(est) else None


def schedule_length(module, configured: int | None, key: str) -> int:
    """``configured`` (``model.<key>``) when set, else the run's steps (at least 1); warns when a set length is
    more than :data:`LONG` times the run's."""
    steps = run_steps(module)
    if configured is None:
        return max(1, steps or 1)
    configured = int(configured)
    if steps and configured > LONG * steps:
        log.warning(
            "model.%s=%d is %.0fx this run's %d steps: the learning rate stays near its start (null: follow "
            "trainer.max_steps)",
            key,
            configured,
            configured / steps,
            steps,
        )
    return configured


def exponential_record(lr: float, lr_decay: float, length: int, steps: int | None) -> dict:
    """What an exponential decay over ``length`` steps does in a run of ``steps``."""
    end = None if steps is None else lr * lr_decay ** (min(steps, 10**12) / length)
    return {"kind": "exponential", "length_steps": length, "run_steps": steps, "lr_start": lr, "lr_end": end}


def cosine_record(lr: float, eta_min: float, length: int, steps: int | None) -> dict:
    """What a cosine schedule of period ``length`` (CosineAnnealingLR) does in a run of ``steps``."""
    end = None if steps is None else eta_min + (lr - eta_min) * (1 + math.cos(math.pi * steps / length)) / 2
    return {"kind": "cosine", "length_steps": length, "run_steps": steps, "lr_start": lr, "lr_end": end}


def is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_rates(lr, lr_decay=None) -> None:
    """Refuse, naming the setting and its value, a learning rate ``model.lr`` that is not a finite number > 0
    (torch's optimiser would take nan, and a negative rate climbs the loss) or a decay factor ``model.lr_decay``
    outside (0, 1]."""
    if not (is_number(lr) and math.isfinite(lr) and lr > 0):
        raise ValueError(f"model.lr={lr}: must be a finite number > 0 (a learning rate)")
    if lr_decay is not None and not (is_number(lr_decay) and 0 < lr_decay <= 1):
        raise ValueError(f"model.lr_decay={lr_decay}: must be in (0, 1] (the factor the learning rate falls by)")
