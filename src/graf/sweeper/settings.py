"""The settings of ``hydra/sweeper=graf_optuna`` (``hydra.sweeper.*``) and their defaults, in one home: the structured
config Hydra registers (:mod:`hydra_plugins.graf_optuna_sweeper`) and the keyword arguments of
:class:`graf.sweeper.optuna_sweeper.OptunaSweep` (:func:`sweeper_settings` outside Hydra)."""

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass
class PrunerConf:
    name: str = "median"  # median | hyperband | none
    monitor: str = "val/psnr"  # the validation metric logged during training that is reported
    n_startup_trials: int = 3  # median: no pruning before this many trials have finished
    n_warmup_steps: int = 0  # median: no pruning before this global step


@dataclass
class HeartbeatConf:
    """Dead workers on a shared RDB storage (PostgreSQL, MySQL): Optuna's heartbeats.  Each running trial's
    worker records a heartbeat every ``interval`` seconds; a RUNNING trial whose last heartbeat is older than
    ``grace_period`` is failed by the next worker that looks (``optuna.storages.fail_stale_trials``) and queued
    again up to ``max_retry`` times (``RetryHeartbeatStaleTrialCallback``).  An SQLite storage keeps the local
    check (the owner's host, pid and start time)."""

    interval: int = 10
    grace_period: int = 60
    max_retry: int = 3


@dataclass
class GrafOptunaSweeperConf:
    _target_: str = "hydra_plugins.graf_optuna_sweeper.graf_optuna_sweeper.GrafOptunaSweeper"
    sampler: str = (
        "auto"  # auto (grid if all params are choices, nsga2 for 2+ objectives, else tpe) | tpe | grid | nsga2 | random
    )
    seed: int = 0
    population_size: int | None = None  # nsga2: trials per generation; null: Optuna's 50
    # null: each objective's own direction (its metric's in graf.metrics.names; a cost's: minimize); or maximize /
    # minimize, a list for several objectives, refused where it contradicts the metric
    direction: Any = None
    storage: str | None = None  # SQLAlchemy URL; null: sqlite:///<sweep dir>/optuna.db
    study_name: str | None = None  # null: the task name
    n_trials: int = 20  # finished trials (complete or pruned) the study ends with, over all runs
    max_failures: int = 5  # failed trials (raised, NaN) tolerated before the sweep stops
    n_jobs: int = 1  # processes running trials at once on this machine (same storage)
    threads_per_job: int | None = None  # torch threads per trial; null: cores // n_jobs
    pruner: PrunerConf = field(default_factory=PrunerConf)
    heartbeat: HeartbeatConf = field(default_factory=HeartbeatConf)  # RDB storages (not SQLite): dead workers
    params: dict[str, str] = field(default_factory=dict)  # the search space: key -> interval/range/choice
    test_best: bool = True  # test the chosen configuration once, after the search (best/)
    test_overrides: list[str] = field(default_factory=lambda: ["test=true"])
    plots: bool = True
    worker_rank: int = 0  # set by the sweeper for the processes n_jobs starts


def sweeper_settings(**overrides: Any) -> dict:
    """Every ``hydra.sweeper`` setting at its default (:class:`GrafOptunaSweeperConf`'s, their one home), with
    ``overrides``: the keyword arguments of :class:`graf.sweeper.optuna_sweeper.OptunaSweep` outside Hydra."""
    settings = {k: v for k, v in asdict(GrafOptunaSweeperConf()).items() if k != "_target_"}
    unknown = set(overrides) - set(settings)
    if unknown:
        raise TypeError(f"not a hydra.sweeper setting: {', '.join(sorted(unknown))}")
    return {**settings, **overrides}
