"""The Optuna sweeper's work (the Hydra plugin, ``hydra_plugins.graf_optuna_sweeper``, is a thin shell).

One study per sweep, stored persistently (default ``sqlite:///<sweep dir>/optuna.db``; any SQLAlchemy URL in
``hydra.sweeper.storage``) under ``hydra.sweeper.study_name`` (default: the task name).  Trials are asked
and told one at a time (ask-and-tell), so that every outcome is stored as it happens:

- **resume**: the same command again continues the study until ``n_trials`` trials are finished
  (COMPLETE or PRUNED) in the storage.  A trial left RUNNING by a process that no longer lives (killed; the
  owner's host, pid and process start time are stored with each trial) is marked FAIL (``graf.interrupted``)
  and its parameters are queued again (``graf.requeued_from``), resuming from the interrupted trial's last
  checkpoint when it has one (``ckpt_path``).
- **failures**: a trial whose job raises, or returns NaN/inf, is stored FAIL (``graf.error``) and the study
  goes on; after ``max_failures`` such trials the sweep stops with an error (the outputs are still written).
- **no configuration trained twice**: parameters equal to a finished trial's are not run again; the trial
  takes that trial's outcome (``graf.duplicate_of``).  Several processes may share one storage (``n_jobs``
  starts them; or start the same command several times): a file lock next to an SQLite storage serialises
  the bookkeeping, and a trial asked beyond ``n_trials`` is dropped (``graf.surplus``).
- **a study shared across machines** (a PostgreSQL or other RDB URL in ``hydra.sweeper.storage``): the owner
  check cannot tell a dead worker on another machine from a live one, so such storages use Optuna's own
  mechanism instead: each worker records a heartbeat for its running trial every ``heartbeat.interval`` seconds,
  a trial silent for ``heartbeat.grace_period`` is failed by the next worker that looks
  (``optuna.storages.fail_stale_trials``) and queued again by ``RetryHeartbeatStaleTrialCallback`` (up to
  ``heartbeat.max_retry`` times; its failure is not counted against ``max_failures``).
- **samplers**: TPE (default), grid (every parameter categorical; ``sampler: grid``, or ``auto``), NSGA-II
  (``auto`` with two or more objectives), random; seeded with ``seed`` plus the number of trials already
  stored plus the worker's rank, so a resumed or parallel sweep does not replay the same proposals.
- **pruning**: each trial's job reports the validation metric logged during training (``monitor``) and
  stops when the pruner (median by default) says so: the trial is stored PRUNED.
- **after the search**: the trials table, the best parameters as an override file, the figures
  (:mod:`graf.sweeper.outputs`), and the chosen configuration tested once (``test_best``: its checkpoint
  validated and tested, ``best/results.json``) -- the only job that sees the test split.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import math
import os
import socket
import subprocess
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import optuna
import psutil
import sqlalchemy.exc
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.core.utils import JobStatus
from omegaconf import DictConfig, OmegaConf
from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback, fail_stale_trials
from optuna.storages._heartbeat import is_heartbeat_enabled  # Optuna's own test, not exported by optuna.storages
from optuna.trial import FrozenTrial, TrialState

from graf.errors import PREEMPTED_EXIT_CODE, is_preempted
from graf.io import atomic_write_json
from graf.search.objectives import check_objective_names, metrics_mean, objective_direction
from graf.search.pruners import make_pruner
from graf.search.search_space import SearchSpace, SearchSpaceError, parse_search_space
from graf.sweeper.outputs import best_trials, write_outputs
from graf.sweeper.settings import HeartbeatConf

log = logging.getLogger("graf")

OWNER, ERROR, INTERRUPTED, REQUEUED, RESUME, DUPLICATE, SURPLUS, OUTPUT, WALL = (
    "graf.owner",
    "graf.error",
    "graf.interrupted",
    "graf.requeued_from",
    "graf.resume_from",
    "graf.duplicate_of",
    "graf.surplus",
    "graf.output_dir",
    "graf.wall_s",
)
NOT_COUNTED = (INTERRUPTED, SURPLUS, DUPLICATE)  # FAIL trials that are not the configuration's failure
POLL_S = 2.0


class SweepError(RuntimeError):
    """The sweep cannot go on (too many failed trials, a storage holding another search)."""


class SweepPreempted(RuntimeError):
    """A trial was stopped by SIGTERM (a cluster pre-empting the job): its parameters are queued again (resuming
    from its checkpoint) and the sweep stops with the pre-emption's exit code; the same command resumes it."""

    exit_code = PREEMPTED_EXIT_CODE


# ----------------------------------------------------------------------------------------------------------
# processes
def _process_start(pid: int) -> float | None:
    try:
        return float(psutil.Process(pid).create_time())
    except Exception:
        return None


def this_owner() -> dict:
    return {"host": socket.gethostname(), "pid": os.getpid(), "start": _process_start(os.getpid())}


def owner_alive(owner: dict | None) -> bool | None:
    """Whether a trial's owning process still runs (None: it ran on another host; unknown)."""
    if not owner:
        return False
    if owner.get("host") != socket.gethostname():
        return None
    start = _process_start(int(owner["pid"]))
    if start is None:
        return False
    return owner.get("start") is None or abs(start - float(owner["start"])) < 1.0


@contextlib.contextmanager
def storage_lock(lock_path: Path | None):
    """An exclusive lock (fcntl) around the bookkeeping of processes sharing an SQLite storage."""
    if lock_path is None:
        yield
        return
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "a+") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _sqlite_path(url: str) -> Path | None:
    return Path(url[len("sqlite:///") :]) if url.startswith("sqlite:///") else None


def make_storage(url: str, heartbeat: dict | None):
    """The study's storage: the URL itself for SQLite (the owner check finds dead workers), an ``RDBStorage``
    with Optuna's heartbeats and retry callback for any other database."""
    if url.startswith("sqlite") or not heartbeat:
        if heartbeat and url.startswith("sqlite"):
            log.info(
                "storage %s is SQLite: hydra.sweeper.heartbeat (interval %s s, grace period %s s) is not used there; "
                "a dead worker's trial is found by its owner's host, pid and start time instead",
                url,
                heartbeat.get("interval"),
                heartbeat.get("grace_period"),
            )
        return url
    interval, grace = int(heartbeat["interval"]), heartbeat.get("grace_period")
    for attempt in range(5):
        try:
            return RDBStorage(
                url,
                heartbeat_interval=interval,
                grace_period=None if grace is None else int(grace),
                heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(max_retry=heartbeat["max_retry"]),
            )
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.ProgrammingError) as exc:
            # workers starting together on an empty database race to create Optuna's tables (one wins, the
            # others' CREATE fails): the schema is there a moment later, so connect again
            if attempt == 4:
                raise
            log.info("the storage's schema is being created by another worker (%s): retrying", type(exc).__name__)
            time.sleep(0.5 + attempt)


def heartbeat_enabled(study) -> bool:
    """Whether the study's storage records heartbeats (an RDB storage made by :func:`make_storage`)."""
    return is_heartbeat_enabled(study._storage)


@contextlib.contextmanager
def heartbeats(study, trial):
    """Record ``trial``'s heartbeat every interval while the block runs (a thread of this worker), when the
    study's storage has heartbeats: the same records ``study.optimize`` makes, for this ask-and-tell loop."""
    if not heartbeat_enabled(study):
        yield
        return
    storage, stop = study._storage, threading.Event()
    interval = storage.get_heartbeat_interval()

    def beat() -> None:
        while True:
            with contextlib.suppress(Exception):  # a dropped connection: the next beat tries again
                storage.record_heartbeat(trial._trial_id)
            if stop.wait(interval):
                return

    t = threading.Thread(target=beat, name=f"heartbeat-trial-{trial.number}", daemon=True)
    t.start()
    try:
        yield
    finally:
        stop.set()
        t.join()


def retried(trials: list[FrozenTrial]) -> set[int]:
    """The numbers of trials failed by their heartbeat and queued again (Optuna's retry history)."""
    return {n for t in trials for n in t.system_attrs.get("retry_history", [])}


# ----------------------------------------------------------------------------------------------------------
def make_sampler(
    name: str,
    space: SearchSpace,
    n_objectives: int,
    seed: int,
    population_size: int | None = None,
    grid_seed: int | None = None,
) -> optuna.samplers.BaseSampler:
    """``seed`` seeds a sampler of this process (varied per run and worker); a grid is shuffled by ``grid_seed``
    instead, the same in every process and run of a study: a trial stores its point as an index into the
    shuffled grid, so another shuffle (a resumed run, a second worker) would read those indices as other points,
    try some twice and leave others out."""
    name = (name or "auto").lower()
    if name == "auto":
        name = "nsga2" if n_objectives > 1 else ("grid" if space.all_categorical else "tpe")
    if name == "tpe":
        return optuna.samplers.TPESampler(seed=seed, multivariate=True)
    if name == "grid":
        if not space.all_categorical:
            raise SearchSpaceError(
                "sampler grid needs every parameter to be a choice(...): "
                f"{', '.join(k for k, d in space.distributions.items() if not hasattr(d, 'choices'))}"
            )
        return _Grid(space.grid(), seed=seed if grid_seed is None else grid_seed)
    if name == "nsga2":
        if population_size is not None and int(population_size) < 2:
            raise SearchSpaceError(f"hydra.sweeper.population_size={population_size}: NSGA-II needs at least 2")
        return optuna.samplers.NSGAIISampler(seed=seed, population_size=int(population_size or 50))
    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    raise SearchSpaceError(f"hydra.sweeper.sampler={name}: one of auto, tpe, grid, nsga2, random")


class _Grid(optuna.samplers.GridSampler):
    """Optuna's grid sampler without its ``study.stop()`` once the grid is covered (only allowed inside
    ``study.optimize``): this sweeper's loop ends the search itself (:meth:`OptunaSweep._next`)."""

    def after_trial(self, study, trial, state, values) -> None:
        return None


def counted_failures(trials: list[FrozenTrial]) -> list[FrozenTrial]:
    """Failed trials that count against ``max_failures``: not those interrupted, surplus or duplicate, nor those
    failed by a stale heartbeat and queued again (their worker died, the configuration did not fail)."""
    again = retried(trials)
    return [
        t
        for t in trials
        if t.state == TrialState.FAIL and not any(k in t.user_attrs for k in NOT_COUNTED) and t.number not in again
    ]


def finished(trials: list[FrozenTrial]) -> list[FrozenTrial]:
    return [t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]


def _quote(s: str) -> str:
    return "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _grammar(v) -> str:
    """A value in Hydra's override grammar (strings quoted, dicts and lists nested)."""
    if isinstance(v, dict):
        return "{" + ",".join(f"{k}:{_grammar(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_grammar(x) for x in v) + "]"
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    return _quote(str(v))


class OptunaSweep:
    """One process's part in a study (see the module doc)."""

    def __init__(
        self,
        *,
        sampler: str,
        seed: int,
        direction: Any,
        storage: str | None,
        study_name: str | None,
        n_trials: int,
        max_failures: int,
        n_jobs: int,
        threads_per_job: int | None,
        pruner: dict | None,
        heartbeat: dict | None,
        params: dict | None,
        test_best: bool,
        population_size: int | None,
        test_overrides: list | None,
        plots: bool,
        worker_rank: int,
    ):
        """The settings of ``hydra.sweeper``, every one given: their defaults have one home, the plugin's config class
        (:class:`graf.sweeper.settings.GrafOptunaSweeperConf`; in code:
        ``OptunaSweep(**sweeper_settings(...))``)."""
        self.sampler_name, self.seed = sampler, int(seed)
        self.direction = direction  # None: each objective's own; checked against the objectives (_objective_names)
        self.directions: list[str] = []  # one per objective, set with the objectives' names
        self.storage, self.study_name = storage, study_name
        self.n_trials, self.max_failures = int(n_trials), int(max_failures)
        self.n_jobs, self.threads_per_job = max(1, int(n_jobs)), threads_per_job
        self.pruner_conf = dict(pruner or {})
        self.heartbeat = dict(heartbeat) if heartbeat is not None else asdict(HeartbeatConf())
        self.params = dict(params or {})
        self.test_best, self.test_overrides = bool(test_best), list(test_overrides or ["test=true"])
        self.plots, self.worker_rank = bool(plots), int(worker_rank)
        self.population_size = population_size
        self.config: DictConfig | None = None
        self.launcher = None
        self.hydra_context = None

    # -- Hydra's side ---------------------------------------------------------------------------------------
    def setup(self, *, hydra_context, task_function, config: DictConfig) -> None:
        self.hydra_context, self.config = hydra_context, config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def _compose(self, overrides: list[str]) -> DictConfig:
        return self.hydra_context.config_loader.load_sweep_config(
            master_config=self.config, sweep_overrides=list(overrides)
        )

    def _launch(self, overrides: list[str], job_idx: int):
        return self.launcher.launch([overrides], initial_job_idx=job_idx)[0]

    # -- the search -----------------------------------------------------------------------------------------
    def threads(self) -> int:
        if self.threads_per_job:
            return int(self.threads_per_job)
        return max(1, (os.cpu_count() or 1) // self.n_jobs)

    def _prune_absent(self, space: SearchSpace) -> SearchSpace:
        """Drop parameters the run's config does not have (a search run with a model that lacks them, e.g.
        the smoke test with model=knn keeps only the neighbor settings)."""
        cfg = self._compose(space.fixed)
        for key in list(space.distributions):
            plain = key.lstrip("+~").split("@")[0]
            if key.startswith("+"):
                continue
            if OmegaConf.select(cfg, plain, default="__absent__") == "__absent__":
                log.info(
                    "search space: %s is not in this run's config (model %s): left out",
                    key,
                    cfg.get("model", {}).get("_target_"),
                )
                del space.distributions[key]
        if not space.distributions:
            raise SearchSpaceError("no parameter of the search space is in this run's config")
        return space

    def _objective_names(self) -> list[str]:
        names = self.config.get("optimized_metric")
        names = [names] if isinstance(names, str) else list(names or [])
        check_objective_names(names)
        own = [objective_direction(n) for n in names]  # the metric registry's (a cost: minimize)
        given = self.direction
        if given is None:
            self.directions = own
            return names
        given = [str(d) for d in (given if isinstance(given, (list, tuple)) or OmegaConf.is_list(given) else [given])]
        for d in given:
            if d not in ("maximize", "minimize"):
                raise SearchSpaceError(f"hydra.sweeper.direction: {d!r} is not maximize or minimize")
        if len(names) != len(given):
            raise SearchSpaceError(
                f"optimized_metric {names} has {len(names)} value(s) but hydra.sweeper.direction "
                f"has {len(given)}: give one direction per objective (or none: each objective's own)"
            )
        for n, d, o in zip(names, given, own):
            if d != o:
                better = "higher" if o == "maximize" else "lower"
                raise SearchSpaceError(
                    f"hydra.sweeper.direction {d} for {n} contradicts the metric ({better} is better: {o}); leave "
                    "direction out and each objective takes its own"
                )
        self.directions = given
        return names

    def sweep(self, arguments: list[str]) -> list:
        """This process's part of the search over the space of ``arguments`` and ``hydra.sweeper.params``; rank 0
        starts the other workers, writes the outputs and tests the chosen configuration.  The trials' returns."""
        sweep_dir = Path(str(self.config.hydra.sweep.dir)).absolute()
        sweep_dir.mkdir(parents=True, exist_ok=True)
        if self.worker_rank == 0:
            OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        names = self._objective_names()
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        space = self._prune_absent(parse_search_space(self.params, arguments, parser))
        study, ctx = self._open_study(sweep_dir, space, names)
        workers = (
            self._start_workers(sweep_dir, ctx["url"], ctx["name"]) if self.worker_rank == 0 and self.n_jobs > 1 else []
        )
        try:
            returns, error = self._trials(study, ctx)
        except SweepPreempted as exc:
            if self.worker_rank == 0:
                write_outputs(study, ctx["sweep_dir"], space, ctx["names"], plots=False)
            log.error("%s", exc)
            raise SystemExit(exc.exit_code) from None
        finally:
            for p in workers:
                p.wait()
        if self.worker_rank == 0:
            self._finish(study, ctx)
        if error is not None:
            raise error
        return returns

    def _open_study(self, sweep_dir: Path, space: SearchSpace, names: list[str]):
        """``(study, ctx)``: the study created or loaded (under the storage lock) with this process's sampler, and
        what the loop needs of the sweep (url, name, sweep_dir, lock, space, n_trials, names)."""
        url = str(self.storage) if self.storage else f"sqlite:///{sweep_dir / 'optuna.db'}"
        name = str(self.study_name or self.config.get("task_name") or "study")
        db = _sqlite_path(url)
        lock = db.with_name(db.name + ".lock") if db is not None else None
        n_trials = self.n_trials
        if (
            self.sampler_name in ("grid",)
            or (self.sampler_name == "auto" and len(names) == 1 and space.all_categorical)
        ) and space.grid_size() < n_trials:
            log.info("the grid has %d points: n_trials %d -> %d", space.grid_size(), n_trials, space.grid_size())
            n_trials = space.grid_size()
        with storage_lock(lock):
            study = optuna.create_study(
                storage=make_storage(url, self.heartbeat),
                study_name=name,
                directions=self.directions,
                load_if_exists=True,
                pruner=make_pruner(self.pruner_conf),
            )
            self._check_same_search(study, space, names)
            study.sampler = make_sampler(
                self.sampler_name,
                space,
                len(names),
                self.seed + len(study.trials) + 7919 * self.worker_rank,
                self.population_size,
                grid_seed=self.seed,
            )
        log.info(
            "study %s in %s: %d trial(s) stored of n_trials=%d; objective %s (%s); threads per trial %d",
            name,
            url,
            len(study.trials),
            n_trials,
            names,
            self.directions,
            self.threads(),
        )
        ctx = {"url": url, "name": name, "sweep_dir": sweep_dir, "lock": lock, "space": space,
               "n_trials": n_trials, "names": names}  # fmt: skip
        return study, ctx

    def _trials(self, study, ctx) -> tuple[list, SweepError | None]:
        """Run trials until the study is done (or waits on others' last trials); the returns, and the error that
        stopped the search (too many failures) or None."""
        returns = []
        while True:
            step = self._next(study, ctx)
            if step == "done":
                return returns, None
            if step == "wait":
                time.sleep(POLL_S)
                continue
            if isinstance(step, SweepError):
                return returns, step
            returns.append(self._run_trial(study, step, ctx))

    def _check_same_search(self, study, space: SearchSpace, names: list[str]) -> None:
        described = {"space": space.describe(), "objectives": names, "directions": self.directions}
        before = study.user_attrs.get("graf.search")
        now = json.loads(json.dumps(described))
        if before is None:
            study.set_user_attr("graf.search", described)
        elif (
            before["space"]["fixed"] != now["space"]["fixed"]
            and {**before, "space": None} == {**now, "space": None}
            and before["space"]["params"] == now["space"]["params"]
        ):
            log.warning(
                "study %s: its earlier trials ran with the settings %s, this run's are %s: the trials may not "
                "be comparable",
                study.study_name,
                before["space"]["fixed"],
                now["space"]["fixed"],
            )
        elif before != now:
            raise SweepError(
                f"study {study.study_name} in this storage was run with another search ({before}); "
                f"this command's is {described}: use another hydra.sweeper.study_name or sweep dir"
            )

    def _start_workers(self, sweep_dir: Path, url: str, name: str) -> list[subprocess.Popen]:
        """``n_jobs - 1`` more processes of the same command on the same storage (rank 1..n-1)."""
        procs = []
        env = dict(os.environ, OMP_NUM_THREADS=str(self.threads()), MKL_NUM_THREADS=str(self.threads()))
        argv = [
            a
            for a in sys.argv[1:]
            if not a.startswith(
                (
                    "hydra.sweep.dir=",
                    "hydra.sweeper.worker_rank=",
                    "hydra.sweeper.storage=",
                    "hydra.sweeper.study_name=",
                )
            )
        ]
        for rank in range(1, self.n_jobs):
            cmd = [
                sys.executable,
                sys.argv[0],
                *argv,
                f"hydra.sweep.dir={_quote(str(sweep_dir))}",
                f"hydra.sweeper.storage={_quote(url)}",
                f"hydra.sweeper.study_name={_quote(name)}",
                f"hydra.sweeper.worker_rank={rank}",
            ]
            f = open(sweep_dir / f"worker_{rank}.log", "ab")
            procs.append(subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env))
            log.info("worker %d started (pid %d): log %s", rank, procs[-1].pid, f.name)
        return procs

    def _recover_interrupted(self, study, ctx) -> None:
        if heartbeat_enabled(study):  # a shared RDB storage: Optuna's heartbeats find dead workers on any machine
            before = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
            fail_stale_trials(study)
            trials = study.get_trials(deepcopy=False)
            for n in sorted(before & retried(trials)):
                log.warning(
                    "trial %d: its worker %s sent no heartbeat for %s s: failed and queued again by Optuna",
                    n,
                    trials[n].user_attrs.get(OWNER),
                    self.heartbeat.get("grace_period") or 2 * int(self.heartbeat["interval"]),
                )
            return
        for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            owner = t.user_attrs.get(OWNER)
            alive = owner_alive(owner)
            if alive or alive is None:
                continue
            if owner is None and t.datetime_start and (time.time() - t.datetime_start.timestamp()) < 60:
                continue  # just asked by another process, its owner not written yet
            log.warning("trial %d: its process %s is gone", t.number, owner)
            try:
                self._requeue(study, t, t.user_attrs.get(OUTPUT))
            except Exception:  # finished meanwhile, or recovered by another process
                continue

    def _requeue(self, study, trial, output_dir: str | None) -> None:
        """A trial that did not end by its own fault (its process killed, or pre-empted): stored as failed but
        not counted as the configuration's failure, and its parameters queued again, resuming from its last
        checkpoint when it has one."""
        storage = study._storage
        storage.set_trial_user_attr(trial._trial_id, INTERRUPTED, True)
        storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
        attrs = {REQUEUED: trial.number}
        ckpt = Path(output_dir) / "checkpoints" / "last.ckpt" if output_dir else None
        if ckpt is not None and ckpt.is_file():
            attrs[RESUME] = str(ckpt)
        study.enqueue_trial(trial.params, user_attrs=attrs)
        log.warning(
            "trial %d was interrupted: stored as failed, its parameters queued again%s",
            trial.number,
            f" (resuming from {ckpt})" if RESUME in attrs else "",
        )

    def _next(self, study, ctx):
        """Under the storage lock: recover interrupted trials, then either ``"done"``, ``"wait"`` (others
        are running the last trials), a :class:`SweepError`, or a new trial to run."""
        with storage_lock(ctx["lock"]):
            self._recover_interrupted(study, ctx)
            trials = study.get_trials(deepcopy=False)
            done = finished(trials)
            failures = counted_failures(trials)
            running = [t for t in trials if t.state == TrialState.RUNNING]
            if len(done) >= ctx["n_trials"]:
                return "done"
            if len(failures) >= self.max_failures:
                return SweepError(
                    f"{len(failures)} trials failed (hydra.sweeper.max_failures={self.max_failures}); "
                    f"last: trial {failures[-1].number}: {failures[-1].user_attrs.get(ERROR)}"
                )
            if len(done) + len(running) >= ctx["n_trials"]:
                return "wait"
            if isinstance(study.sampler, _Grid) and not any(t.state == TrialState.WAITING for t in trials):
                visited = {
                    tuple(sorted(t.params.items()))
                    for t in trials
                    if t.state != TrialState.WAITING and SURPLUS not in t.user_attrs
                }
                if len(visited) >= ctx["space"].grid_size():
                    if running:
                        return "wait"
                    log.warning(
                        "the grid's %d points are all tried (%d finished, %d failed): the search ends",
                        ctx["space"].grid_size(),
                        len(done),
                        len(failures),
                    )
                    return "done"
            trial = study.ask(ctx["space"].distributions)
            if heartbeat_enabled(study):  # a trial with no heartbeat at all is never found stale: beat once now
                study._storage.record_heartbeat(trial._trial_id)
            trial.set_user_attr(OWNER, this_owner())
            earlier = [
                t
                for t in study.get_trials(deepcopy=False)
                if t.number < trial.number and t.state in (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING)
            ]
            if len(earlier) >= ctx["n_trials"]:
                trial.set_user_attr(SURPLUS, True)
                study.tell(trial, state=TrialState.FAIL)
                return "wait"
            return trial

    def _duplicate(self, study, trial) -> FrozenTrial | None:
        """A finished or running trial (not this one) with the same parameters, once it has finished."""
        while True:
            same = [
                t
                for t in study.get_trials(deepcopy=False)
                if t.number != trial.number
                and t.params == trial.params
                and (
                    t.state in (TrialState.COMPLETE, TrialState.PRUNED)
                    or (t.state == TrialState.RUNNING and OWNER in t.user_attrs)
                )
            ]
            if not same:
                return None
            done = [t for t in same if t.state != TrialState.RUNNING]
            if done:
                return done[0]
            time.sleep(POLL_S)  # the same configuration is being trained elsewhere: take its outcome

    def _run_trial(self, study, trial, ctx):
        """Run one trial's job (unless a finished trial had its parameters: its outcome is taken) and tell the
        study its outcome; the job's return (None for a duplicate)."""
        if self._took_duplicate(study, trial):
            return None
        space: SearchSpace = ctx["space"]
        overrides = self._trial_overrides(trial, ctx)
        log.info("trial %d: %s", trial.number, " ".join(space.overrides(trial.params)[len(space.fixed) :]))
        t0 = time.perf_counter()
        with heartbeats(study, trial):
            ret = self._launch(overrides, trial.number)
        wall = round(time.perf_counter() - t0, 3)
        trial.set_user_attr(WALL, wall)
        with contextlib.suppress(Exception):
            trial.set_user_attr(OUTPUT, str(ret.hydra_cfg.hydra.runtime.output_dir))
        if ret.status == JobStatus.COMPLETED:
            self._tell_values(study, trial, ret._return_value, ctx, wall)
        else:
            self._tell_failure(study, trial, ret)
        return ret

    def _took_duplicate(self, study, trial) -> bool:
        """Whether a finished trial had the same parameters: its outcome is then told for this one."""
        dup = self._duplicate(study, trial)
        if dup is None:
            return False
        trial.set_user_attr(DUPLICATE, dup.number)
        if dup.state == TrialState.COMPLETE:
            study.tell(trial, dup.values)
        else:
            study.tell(trial, state=TrialState.PRUNED)
        log.info(
            "trial %d: the parameters of trial %d (%s): its outcome taken, nothing trained",
            trial.number,
            dup.number,
            dup.state.name,
        )
        return True

    def _trial_overrides(self, trial, ctx) -> list[str]:
        """The job's overrides: the trial's parameters, its checkpoint to resume from, its link to the study
        (``optuna_trial``: the pruner's reports) and its threads."""
        overrides = ctx["space"].overrides(trial.params)
        resume = trial.user_attrs.get(RESUME)
        if resume and Path(resume).is_file():
            overrides.append(f"ckpt_path={_quote(resume)}")
        prune = len(self.directions) == 1 and str(self.pruner_conf.get("name", "none")) != "none"
        trial_conf = {
            "storage": ctx["url"],
            "study_name": ctx["name"],
            "trial_id": trial._trial_id,
            "number": trial.number,
            "monitor": self.pruner_conf.get("monitor", "val/psnr") if prune else None,
            "pruner": {k: v for k, v in self.pruner_conf.items() if k != "monitor"},
        }
        return overrides + [
            f"{self._key('optuna_trial')}={_grammar(trial_conf)}",
            f"{self._key('torch_threads')}={self.threads()}",
        ]

    def _tell_values(self, study, trial, values, ctx, wall: float) -> None:
        """A completed job's objective values told; one not a finite number per objective is a failed trial."""
        values = list(values) if isinstance(values, (list, tuple)) or OmegaConf.is_list(values) else [values]
        try:
            values = [float(v) for v in values]
        except (TypeError, ValueError):
            values = [math.nan]
        if len(values) != len(self.directions) or not all(math.isfinite(v) for v in values):
            trial.set_user_attr(ERROR, f"objective {ctx['names']} returned {values}")
            study.tell(trial, state=TrialState.FAIL)
            log.warning(
                "trial %d failed: its objective is %s (stored as failed; the study goes on)", trial.number, values
            )
        else:
            study.tell(trial, values)
            log.info("trial %d: %s = %s (%.1f s)", trial.number, ctx["names"], values, wall)

    def _tell_failure(self, study, trial, ret) -> None:
        """A job that raised: pruned, pre-empted (queued again, and the sweep stops: :class:`SweepPreempted`), or
        failed."""
        exc = ret._return_value
        if isinstance(exc, optuna.TrialPruned):
            study.tell(trial, state=TrialState.PRUNED)
            log.info("trial %d pruned: %s", trial.number, exc)
        elif is_preempted(exc):
            has_cfg = getattr(ret, "hydra_cfg", None) is not None
            self._requeue(study, trial, str(ret.hydra_cfg.hydra.runtime.output_dir) if has_cfg else None)
            raise SweepPreempted(
                f"trial {trial.number} was pre-empted ({exc}); its parameters are queued again: "
                "run the same command to resume the search"
            )
        else:
            trial.set_user_attr(ERROR, f"{type(exc).__name__}: {exc}"[:2000])
            study.tell(trial, state=TrialState.FAIL)
            log.warning(
                "trial %d failed: %s: %s (stored as failed; the study goes on)", trial.number, type(exc).__name__, exc
            )

    def _key(self, key: str) -> str:
        return key if key in self.config else f"+{key}"

    # -- after the search -----------------------------------------------------------------------------------
    def _finish(self, study, ctx) -> None:
        """The outputs written, and the chosen configuration tested once (``best/best.json``), unless it was."""
        out = ctx["sweep_dir"]
        space: SearchSpace = ctx["space"]
        write_outputs(study, out, space, ctx["names"], plots=self.plots)
        best = best_trials(study)
        if not best or not self.test_best:
            return
        chosen = best[0]
        record = out / "best" / "best.json"
        before = json.loads(record.read_text()) if record.is_file() else {}
        if before.get("trial") == chosen.number:
            log.info("the chosen trial %d was tested before: %s", chosen.number, record)
            if "metrics@mean" not in before and (means := metrics_mean(before.get("evaluations", []))):
                before["metrics@mean"] = means  # a record from before the means were written: from its evaluations
                atomic_write_json(record, before)
            return
        overrides = (
            space.overrides(chosen.params) + list(self.test_overrides) + ["hydra.sweep.subdir=best", "validate=true"]
        )
        ckpt = Path(chosen.user_attrs.get(OUTPUT, "")) / "checkpoints" / "last.ckpt"
        if chosen.user_attrs.get(OUTPUT) and ckpt.is_file():
            overrides.append(f"ckpt_path={_quote(str(ckpt))}")  # its final weights: resumed at the last step
        overrides.append(f"{self._key('torch_threads')}={self.threads()}")
        log.info("testing the chosen configuration (trial %d) once: %s", chosen.number, " ".join(overrides))
        ret = self._launch(overrides, 10**6)
        result = {
            "trial": chosen.number,
            "params": chosen.params,
            "objectives": ctx["names"],
            "values": chosen.values,
            "overrides": overrides,
            "checkpoint": str(ckpt) if ckpt.is_file() else None,
        }
        _add_test_result(result, ret)
        record.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(record, result)
        shown = result.get("metrics@mean") or result.get("metrics") or {}
        log.info(
            "chosen configuration: trial %d, %s; objective %s; validation PSNR %s, test PSNR %s%s",
            chosen.number,
            chosen.params,
            chosen.values,
            shown.get("val/psnr"),
            shown.get("test/psnr"),
            " (means over the evaluated scenes)" if "metrics@mean" in result else "",
        )


def _add_test_result(result: dict, ret) -> None:
    """The chosen configuration's test job into its record: its figures (and their means over the evaluated
    scenes), or its error."""
    if ret.status != JobStatus.COMPLETED:
        result["error"] = f"{type(ret._return_value).__name__}: {ret._return_value}"
        log.error("testing the chosen configuration failed: %s", result["error"])
        return
    res = Path(str(ret.hydra_cfg.hydra.runtime.output_dir)) / "results.json"
    if res.is_file():
        r = json.loads(res.read_text())
        result["metrics"] = r.get("metrics")
        result["evaluations"] = [
            {"eval_scene": e["eval_scene"], "metrics": e["metrics"]} for e in r.get("evaluations", [])
        ]
        result["results"] = str(res)
        if means := metrics_mean(result["evaluations"]):
            result["metrics@mean"] = means
