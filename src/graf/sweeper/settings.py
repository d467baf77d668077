"""The settings of ``hydra/sweeper=graf_optuna`` (``hydra.sweeper.*``), each with its default and its meaning, in
one home: the structured config Hydra registers (:mod:`hydra_plugins.graf_optuna_sweeper`), the keyword arguments
of :class:`graf.sweeper.optuna_sweeper.OptunaSweep` (:func:`sweeper_settings` outside Hydra) and the table on the
searches page (:func:`settings_rows`, read when the site is built)."""

from dataclasses import MISSING, asdict, dataclass, field, fields, is_dataclass
from typing import Any


def setting(default: Any = MISSING, help: str = "", default_factory: Any = MISSING) -> Any:  # noqa: A002
    """A field with its meaning (``help``), shown beside its default on the searches page."""
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata={"help": help})
    return field(default=default, metadata={"help": help})


@dataclass
class PrunerConf:
    name: str = setting("median", "`median`, `hyperband` or `none`")
    monitor: str = setting("val/psnr", "the validation metric logged during training that each trial reports")
    n_startup_trials: int = setting(3, "median: no pruning before this many trials have finished")
    n_warmup_steps: int = setting(0, "median: no pruning before this global step")


@dataclass
class HeartbeatConf:
    """Dead workers on a shared RDB storage (PostgreSQL, MySQL): Optuna's heartbeats.  An SQLite storage keeps the
    local check (the owner's host, pid and start time)."""

    interval: int = setting(10, "RDB storages: each running trial's worker records a heartbeat this often (s)")
    grace_period: int = setting(
        60,
        "a running trial with no heartbeat for this long (s) is failed by the next worker that looks "
        "(`optuna.storages.fail_stale_trials`)",
    )
    max_retry: int = setting(
        3, "how often such a trial's parameters are queued again (`RetryHeartbeatStaleTrialCallback`)"
    )


@dataclass
class GrafOptunaSweeperConf:
    _target_: str = "hydra_plugins.graf_optuna_sweeper.graf_optuna_sweeper.GrafOptunaSweeper"
    sampler: str = setting(
        "auto",
        "`auto`: grid when every parameter is a choice, NSGA-II for two or more objectives, TPE otherwise; or "
        "`tpe`, `grid`, `nsga2`, `random`",
    )
    seed: int = setting(
        0, "the sampler's seed (a resumed run or another worker derives its own from it and the trials stored)"
    )
    population_size: int | None = setting(None, "NSGA-II: trials per generation; null: Optuna's 50")
    direction: Any = setting(
        None,
        "null: each objective's metric's direction (the metric registry's; a cost is minimised); given "
        "(`maximize`/`minimize`, a list for several objectives), it must agree with the metric or the search "
        "stops with one line",
    )
    storage: str | None = setting(None, "any SQLAlchemy URL; null: `sqlite:///<sweep dir>/optuna.db`")
    study_name: str | None = setting(None, "the study in the storage; null: the task name")
    n_trials: int = setting(
        20, "finished trials (complete + pruned) the study ends with, over all runs (each search sets its own)"
    )
    max_failures: int = setting(
        5, "failed trials (raised, NaN objective) tolerated before the sweep stops with an error"
    )
    n_jobs: int = setting(1, "trials at once on this machine: more worker processes on the same storage")
    threads_per_job: int | None = setting(None, "torch (and OpenMP) threads of each trial; null: cores // `n_jobs`")
    pruner: PrunerConf = setting(default_factory=PrunerConf, help="pruning of trials by their validation reports")
    heartbeat: HeartbeatConf = setting(default_factory=HeartbeatConf, help="dead workers on an RDB storage")
    params: dict[str, str] = setting(default_factory=dict, help="the search space: key -> interval/range/choice")
    test_best: bool = setting(True, "validate and test the chosen configuration once after the search, into `best/`")
    test_overrides: list[str] = setting(default_factory=lambda: ["test=true"], help="the overrides of that test job")
    plots: bool = setting(True, "write the study's figures")
    worker_rank: int = setting(0, "set by the sweeper for the processes `n_jobs` starts")


def sweeper_settings(**overrides: Any) -> dict:
    """Every ``hydra.sweeper`` setting at its default (:class:`GrafOptunaSweeperConf`'s, their one home), with
    ``overrides``: the keyword arguments of :class:`graf.sweeper.optuna_sweeper.OptunaSweep` outside Hydra."""
    settings = {k: v for k, v in asdict(GrafOptunaSweeperConf()).items() if k != "_target_"}
    unknown = set(overrides) - set(settings)
    if unknown:
        raise TypeError(f"not a hydra.sweeper setting: {', '.join(sorted(unknown))}")
    return {**settings, **overrides}


def settings_rows(conf: Any = GrafOptunaSweeperConf, prefix: str = "") -> list[tuple[str, Any, str]]:
    """``(key, default, meaning)`` of every setting, nested ones as ``pruner.name``, in the class's order."""
    rows = []
    for f in fields(conf):
        if f.name == "_target_":
            continue
        default = f.default_factory() if f.default_factory is not MISSING else f.default
        if is_dataclass(default):
            rows += settings_rows(type(default), f"{prefix}{f.name}.")
        else:
            rows.append((prefix + f.name, default, f.metadata.get("help", "")))
    return rows
