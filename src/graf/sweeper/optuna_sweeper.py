"""The Optuna sweeper's loop (the Hydra plugin, ``hydra_plugins.graf_optuna_sweeper``, is a thin shell).

One study per sweep, stored persistently (default ``sqlite:///<sweep dir>/optuna.db``; any SQLAlchemy URL in
``hydra.sweeper.storage``, :mod:`graf.sweeper.storage`) under ``hydra.sweeper.study_name`` (default: the task
name).  Trials are asked and told one at a time (ask-and-tell), so that every outcome is stored as it happens:

- **resume**: the same command again continues the study until ``n_trials`` trials are finished (COMPLETE or
  PRUNED).  A trial left RUNNING by a worker that is gone is failed and queued again, resuming from its last
  checkpoint (:mod:`graf.sweeper.recovery`; on a shared RDB storage, Optuna's heartbeats find dead workers).
- **failures**: a trial whose job raises, or returns NaN/inf, is stored FAIL (``graf.error``) and the study
  goes on; after ``max_failures`` such trials the sweep stops with an error (the outputs are still written).
- **no configuration trained twice**: a trial whose parameters a finished trial had takes that trial's outcome.
  Several processes may share one storage (``n_jobs`` starts them, :mod:`graf.sweeper.workers`; or start the same
  command several times): a file lock serialises an SQLite storage's bookkeeping, and a trial asked beyond
  ``n_trials`` is dropped (``graf.surplus``).
- **samplers** (:mod:`graf.sweeper.sampler`) and **pruning**: each trial's job reports the validation metric
  logged during training (``monitor``) and stops when the pruner (median by default) says so: stored PRUNED.
- **after the search** (:mod:`graf.sweeper.best`): the trials table, the best parameters as an override file,
  the figures, and the chosen configuration tested once -- the only job that sees the test split.

Settings and their defaults: :class:`graf.sweeper.settings.GrafOptunaSweeperConf`, their one home.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import optuna
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.core.utils import JobStatus
from omegaconf import DictConfig, OmegaConf
from optuna.trial import TrialState

from graf.search.objectives import check_objective_names, objective_directions
from graf.search.pruners import make_pruner
from graf.search.search_space import SearchSpace, SearchSpaceError, parse_search_space
from graf.sweeper.best import finish
from graf.sweeper.outcomes import SweepPreempted, tell_failure, tell_values
from graf.sweeper.outputs import write_outputs
from graf.sweeper.recovery import recover_interrupted, took_duplicate
from graf.sweeper.sampler import Grid, make_sampler
from graf.sweeper.settings import HeartbeatConf
from graf.sweeper.storage import heartbeat_enabled, heartbeats, make_storage, sqlite_path, storage_lock
from graf.sweeper.trials import (
    ERROR,
    OUTPUT,
    OWNER,
    POLL_S,
    RESUME,
    SURPLUS,
    WALL,
    counted_failures,
    finished,
    grammar,
    quote,
)
from graf.sweeper.workers import start_workers, this_owner

log = logging.getLogger("graf")


class SweepError(RuntimeError):
    """The sweep cannot go on (too many failed trials, a storage holding another search)."""


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
        """The objectives' names (``optimized_metric``), their directions set (the metric registry's, or
        ``direction`` checked against them: :func:`graf.search.objectives.objective_directions`)."""
        names = self.config.get("optimized_metric")
        names = [names] if isinstance(names, str) else list(names or [])
        check_objective_names(names)
        given = self.direction
        if OmegaConf.is_list(given):
            given = list(given)
        self.directions = objective_directions(names, given)
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
        workers = []
        if self.worker_rank == 0 and self.n_jobs > 1:
            workers = start_workers(self.n_jobs, self.threads(), sweep_dir, ctx["url"], ctx["name"])
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
            finish(
                study,
                ctx,
                self._launch,
                plots=self.plots,
                test_best=self.test_best,
                test_overrides=self.test_overrides,
                threads=f"{self._key('torch_threads')}={self.threads()}",
            )
        if error is not None:
            raise error
        return returns

    def _open_study(self, sweep_dir: Path, space: SearchSpace, names: list[str]):
        """``(study, ctx)``: the study created or loaded (under the storage lock) with this process's sampler, and
        what the loop needs of the sweep (url, name, sweep_dir, lock, space, n_trials, names)."""
        url = str(self.storage) if self.storage else f"sqlite:///{sweep_dir / 'optuna.db'}"
        name = str(self.study_name or self.config.get("task_name") or "study")
        db = sqlite_path(url)
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

    def _next(self, study, ctx):
        """Under the storage lock: recover interrupted trials, then either ``"done"``, ``"wait"`` (others
        are running the last trials), a :class:`SweepError`, or a new trial to run."""
        with storage_lock(ctx["lock"]):
            recover_interrupted(study, self.heartbeat)
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
            if isinstance(study.sampler, Grid) and not any(t.state == TrialState.WAITING for t in trials):
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

    def _run_trial(self, study, trial, ctx):
        """Run one trial's job (unless a finished trial had its parameters: its outcome is taken) and tell the
        study its outcome; the job's return (None for a duplicate)."""
        if took_duplicate(study, trial):
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
            tell_values(study, trial, ret._return_value, ctx["names"], wall)
        else:
            tell_failure(study, trial, ret)
        return ret

    def _trial_overrides(self, trial, ctx) -> list[str]:
        """The job's overrides: the trial's parameters, its checkpoint to resume from, its link to the study
        (``optuna_trial``: the pruner's reports) and its threads."""
        overrides = ctx["space"].overrides(trial.params)
        resume = trial.user_attrs.get(RESUME)
        if resume and Path(resume).is_file():
            overrides.append(f"ckpt_path={quote(resume)}")
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
            f"{self._key('optuna_trial')}={grammar(trial_conf)}",
            f"{self._key('torch_threads')}={self.threads()}",
        ]

    def _key(self, key: str) -> str:
        return key if key in self.config else f"+{key}"
