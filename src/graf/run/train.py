"""graf-train's task: fit the model when it has parameters, then test it; writes results.json.

Fine-tuning (:mod:`graf.run.finetune`) starts from a checkpoint's weights; resuming (``ckpt_path``,
:mod:`graf.run.resume`) continues a checkpoint's training.  A run started in a folder that holds a finished run
moves that run's files aside first (:func:`graf.run.writer.set_aside_finished`), unless it resumes that run.

Study jobs set ``skip_finished=true``: a job whose output folder already holds its ``results.json`` (or a
``skipped.json``) returns that result without running again, so an interrupted multirun started again with
the same command runs only the jobs that have not finished.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path

import lightning
from hydra import compose
from lightning.pytorch.callbacks import Timer
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig

from graf.app.config import output_dir, task_wrapper
from graf.app.spec import RunSpec, family
from graf.callbacks import Preemption, TargetCount, ThreadsBesideLoad, TrainingInterrupted
from graf.data.splits import mixed_seed
from graf.errors import ConfigError
from graf.interrupts import stage
from graf.io import atomic_write_json
from graf.models.base import CheckpointError, read_checkpoint, safe_loading
from graf.run.budgets import with_study_budget
from graf.run.build import BuiltRun, build
from graf.run.finetune import finetune_record, job_overrides, load_weights
from graf.run.record import Results, Resumed, RunFacts, RunResult, Timing, Training, finished_scene_metrics
from graf.run.resolve import resolve_run
from graf.run.resume import check_resume, interrupted, not_done, preempted, tested_after_training
from graf.run.writer import set_aside_finished, test_and_report

log = logging.getLogger("graf")


@task_wrapper
def train(cfg: DictConfig) -> Results:
    """Fit the model when it has parameters (or fine-tune, or nothing for a zero-shot test), then validate and
    test it beside its baselines and write ``results.json``.  A Ctrl+C says its stage, what was kept and how to
    go on (:mod:`graf.interrupts`)."""
    started = time.perf_counter()
    out = output_dir(cfg)
    cfg = with_study_budget(cfg)
    not_run = job_not_run(cfg, out)
    if not_run is not None:
        return not_run
    aside: list[Path] = []
    with stage("set-up", lambda: not_done(out, aside, "nothing was trained")):
        cfg, built, resumed, zero_shot = set_up(cfg, out, aside)
    ft = cfg.get("finetune") or {}
    if zero_shot:
        log.info("finetune=none: testing %s zero-shot (no step trained)", ft.init_from)
        timing, training = Timing(), None
    else:
        with stage("training", lambda: not_done(out, aside, "results.json was not written")):
            timing, training = fit(built, resumed.global_step if resumed else 0)
    tuned = finetune_record(cfg, built.datamodule, timing.fit_steps or 0) if ft.get("init_from") else None
    # the final weights are validated and tested (nothing is chosen on the test split)
    with stage("testing", lambda: tested_after_training(built, training is not None)):
        facts = RunFacts("train", started, timing, training, resumed, tuned)
        return Results(*test_and_report(built.cfg, built, facts))


def set_up(cfg: DictConfig, out: Path, aside: list[Path]) -> tuple[DictConfig, BuiltRun, Resumed | None, bool]:
    """The run resolved (:func:`graf.run.resolve.resolve_run`), its base model trained first when it is missing,
    the built run, the checkpoint it resumes (checked) and whether it is a zero-shot test (``finetune=none``).  A
    finished run's files in ``out`` are moved aside first (their folder is added to ``aside``), unless this run
    resumes it."""
    spec = resolve_run(cfg)  # every check before a finished run's files are moved aside
    cfg = spec.cfg
    ft = cfg.get("finetune") or {}
    if ft.get("init_from"):
        ensure_base(cfg)
    if not is_inside(cfg.get("ckpt_path"), out):  # a resume of the run in this folder keeps its files
        aside += [p for p in [set_aside_finished(out, [ft.get("init_from")])] if p]
    zero_shot = bool(ft.get("init_from")) and ft.get("fraction") is None  # finetune=none
    built = build(spec, trains=not zero_shot)
    if ft.get("init_from"):
        load_weights(built.model, ft.init_from)
    # resume: refuse another class's, an old layout's or other settings' checkpoint up front
    resumed = check_resume(cfg, built.model, built.datamodule, cfg.ckpt_path) if cfg.get("ckpt_path") else None
    return cfg, built, resumed, zero_shot


def job_not_run(cfg: DictConfig, out: Path) -> Results | None:
    """A study job that is not run: finished before (``skip_finished``), or skipped (:func:`skip_reason`)."""
    if cfg.get("skip_finished"):
        done = finished_result(out)
        if done is not None:
            log.info("%s: finished before (%s); not run again", out, done.get("skipped") or "results.json")
            warn_other_length(cfg, out, done)
            run = RunResult(out, finished_before=True, scene_metrics=finished_scene_metrics(done))
            return Results(done.get("metrics", {}), run)
    reason = skip_reason(cfg)
    if reason:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(out / "skipped.json", {"skipped": reason})
        log.info("%s: skipped: %s", out, reason)
        return Results({}, RunResult(out, skipped=reason))
    return None


def warn_other_length(cfg: DictConfig, out: Path, done: dict) -> None:
    """One warning line when a finished job kept by ``skip_finished`` trained another number of steps than the job
    would train now (a study budget changed since; a job folder's name need not say its steps)."""
    trained = (done.get("training") or {}).get("max_steps")
    if trained is None or (cfg.get("finetune") or {}).get("init_from"):  # fine-tuning sets its own steps later
        return
    now = cfg.get("trainer", {}).get("max_steps")
    if now is not None and int(now) != int(trained):
        log.warning(
            "%s trained %s steps, and this job would train %s now: kept as it is; move the folder away to train %s",
            out,
            trained,
            now,
            now,
        )


def is_inside(path, folder: Path) -> bool:
    return bool(path) and folder.resolve() in Path(str(path)).resolve().parents


FIT_STREAM = 2  # mixed_seed(seed, FIT_STREAM): the fit's global generators (0 and 1 are the data stream's)


def fit(built: BuiltRun, step0: int) -> tuple[Timing, Training | None]:
    """Train the built model (resuming ``ckpt_path`` when given, from step ``step0``) when it has parameters:
    the fit's timing and the training record.  A SIGTERM or Ctrl+C during the fit stops the command with its
    state saved and the way to resume it."""
    model, trainer, cfg = built.model, built.trainer, built.cfg
    if not model.has_trainable_parameters:
        log.info("%s has no trainable parameters: nothing to fit, testing directly", type(model).__name__)
        return Timing(), None
    if cfg.get("seed") is not None:  # the fit's global random stream (dropout, ...) from the seed alone, not from
        # what ran since the model was made (loading a checkpoint's weights, the loggers' set-up)
        lightning.seed_everything(mixed_seed(int(cfg.seed), FIT_STREAM) % 2**32, workers=True, verbose=False)
    t0 = time.perf_counter()
    try:
        with safe_loading():  # a resumed checkpoint: weights only (read_checkpoint has checked it already)
            trainer.fit(model=model, datamodule=built.datamodule, ckpt_path=cfg.get("ckpt_path"), weights_only=True)
    except SIGTERMException:
        raise preempted(cfg, trainer, step0, time.perf_counter() - t0) from None
    except TrainingInterrupted:
        raise interrupted(cfg, trainer) from None
    except SystemExit:  # Lightning's answer to a KeyboardInterrupt (a second Ctrl+C, or no Preemption callback)
        if trainer.interrupted:
            raise interrupted(cfg, trainer) from None
        raise
    if any(isinstance(cb, Preemption) and cb.interrupted for cb in trainer.callbacks):  # Ctrl+C after the last step
        raise interrupted(cfg, trainer)
    fit_s, steps = time.perf_counter() - t0, max(0, trainer.global_step - step0)
    check_last_checkpoint(trainer, built.output_dir)
    timing = Timing(
        fit_s=round(fit_s, 3), fit_steps=int(steps), fit_s_per_step=round(fit_s / steps, 4) if steps else None
    )
    return timing, training_record(trainer, step0)


def check_last_checkpoint(trainer, out: Path) -> None:
    """After a finished fit: the ``last.ckpt`` that every reader opens (fine-tuning from a study's base,
    graf-curves' next point, a search's best trial) must hold the weights training ended with.  Refuse, naming
    the files, when it holds another step (e.g. a pre-emption's checkpoint left behind while the final weights
    went to a versioned copy); a finished run's stale ``preempted.json`` is removed."""
    for cb in getattr(trainer, "checkpoint_callbacks", []):
        if not getattr(cb, "save_last", False) or not getattr(cb, "dirpath", None):
            continue
        last, step = Path(cb.dirpath) / "last.ckpt", int(trainer.global_step)
        if cb.last_model_path and Path(cb.last_model_path) != last:  # a versioned copy (last-v1.ckpt)
            fix = (
                f"its final weights went to {cb.last_model_path}: keep "
                "callbacks.model_checkpoint.enable_version_counter=false"
            )
        else:
            fix = (
                "its checkpoint callback did not save the final step: keep callbacks.model_checkpoint._target_="
                "graf.callbacks.FinalCheckpoint"
            )
        require_step(last, step, f"training ended at step {step} ({fix}); readers of last.ckpt would get stale weights")
    stale = out / "preempted.json"
    if stale.is_file():
        log.info("%s: the pre-empted run has finished; removing its preempted.json", out)
        stale.unlink()


def training_record(trainer, step0: int) -> Training:
    """What results.json records of the training length (``training``): the steps asked and reached, and why
    training stopped before ``max_steps`` when it did.  A stop that is not the user's own limit
    (``trainer.max_epochs``, ``trainer.max_time``) is warned about loudly."""
    asked, epochs = int(trainer.max_steps), int(trainer.max_epochs if trainer.max_epochs is not None else -1)
    reached = int(trainer.global_step)
    rec = Training(
        max_steps=asked,
        max_epochs=epochs,
        start_step=int(step0),
        global_step=reached,
        steps_trained=reached - int(step0),
        epochs_trained=int(trainer.current_epoch),
        stopped_early=False,
        world_size=int(trainer.world_size),
    )
    counted = next((cb for cb in trainer.callbacks if isinstance(cb, TargetCount) and cb.targets is not None), None)
    if counted is not None:  # measured, over every rank: batch_size x world_size per step
        rec.targets_seen = counted.targets
    fewer = sum(cb.fewer_batches for cb in trainer.callbacks if isinstance(cb, ThreadsBesideLoad))
    if fewer:  # the run's last bits may differ from a quiet run's of the same seed and threads
        rec.batches_on_fewer_threads = fewer
    if asked > 0 and reached < asked:
        if epochs > 0 and trainer.current_epoch >= epochs:
            reason, own = (
                (
                    f"trainer.max_epochs={epochs} reached first ({trainer.num_training_batches} steps per "
                    "epoch): your own limit"
                ),
                True,
            )
        elif any(isinstance(cb, Timer) and cb.time_remaining() <= 0 for cb in trainer.callbacks):
            reason, own = "trainer.max_time reached first: your own limit", True
        else:
            reason, own = "a callback stopped training (trainer.should_stop) before trainer.max_steps", False
        rec.stopped_early, rec.stop_reason, rec.own_limit = True, reason, own
        msg = f"training stopped at step {reached} of trainer.max_steps={asked}: {reason}"
        if own:
            log.info(msg)
        else:
            log.warning("WARNING: %s; results.json records it under 'training'", msg)
            print(f"WARNING: {msg}", file=sys.stderr)
    return rec


def finished_result(out: Path) -> dict | None:
    """The finished result in a job folder (``results.json``, or ``skipped.json``), or None."""
    for name in ("results.json", "skipped.json"):
        f = out / name
        if f.is_file():
            try:
                return json.loads(f.read_text())
            except json.JSONDecodeError:
                log.warning("%s is unreadable: running the job again", f)
    return None


def skip_reason(cfg: DictConfig) -> str | None:
    """Why a study job is not run (None: it is).  ``single_seed``: a job of a model trained with one seed only
    (``single_seed.targets``: NeRF2 in the studies) at another seed.  ``same_family_only``: a job whose test
    scenes are of no training scene's layout family (conference_v1 -> office_v2).  ``finetune.base.band=scene``
    (start from a model trained at the new scene's own band) differs from the run's band only for a scene with a
    fixed band (measured data: rfid_s23 at 915 MHz); for a simulated scene it would repeat the job with the run's
    band."""
    if cfg.get("same_family_only"):
        spec = RunSpec.of(cfg)
        train = {family(n) for n in spec.scene_names}
        test = {family(n) for n in spec.eval_scene_names}
        if test and not test & train:
            return (
                f"same_family_only: test scenes of family {', '.join(sorted(test))}, training scenes of "
                f"{', '.join(sorted(train))}"
            )
    one = cfg.get("single_seed") or {}
    target = str((cfg.get("model") or {}).get("_target_"))
    if one and target in set(one.get("targets") or []) and int(cfg.get("seed") or 0) != int(one.get("seed", 0)):
        return f"single_seed: {target} is trained with seed {one.get('seed', 0)} only (a per-scene model)"
    base = (cfg.get("finetune") or {}).get("base") or {}
    if base.get("band") != "scene":
        return None
    if not any(s.get("fixed_band") for s in RunSpec.of(cfg).scenes):
        return "finetune.base.band=scene on a scene simulated at any band: the same job as the one with the run's band"
    return None


def ensure_base(cfg: DictConfig) -> None:
    """Train ``finetune.init_from`` first when ``finetune.base`` says how and it is not finished: a graf-train
    run composed from the job's shared settings (:func:`job_overrides`) and ``finetune.base.overrides`` into
    ``finetune.base.folder`` (resumed from its last checkpoint when an earlier attempt was killed).  A base
    folder trained with other settings is refused, not silently reused."""
    base = cfg.finetune.get("base")
    if not base or not base.get("folder"):
        return
    folder = Path(str(base.folder))
    overrides = job_overrides() + [str(o) for o in (base.get("overrides") or [])]
    if base.get("band_name"):
        overrides.append(f"band={base.band_name}")
    overrides += [
        "finetune=none",
        "finetune.init_from=null",
        "finetune.base=null",
        f"paths.output_dir={folder}",
        "skip_finished=false",
    ]
    record = folder / "base_overrides.json"
    if record.is_file():
        before = json.loads(record.read_text())
        if before != overrides:
            raise ConfigError(
                f"{folder}: a base model trained with other settings is there ({' '.join(before)}); "
                f"this job needs {' '.join(overrides)}: remove that folder or use another "
                "hydra.sweep.dir"
            )
    if (folder / "results.json").is_file():
        check_base_checkpoint(folder)
        return
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(record, overrides)
    last = folder / "checkpoints" / "last.ckpt"
    log.info("training the base model of this job first, in %s: %s", folder, " ".join(overrides))
    base_cfg = compose(config_name="train", overrides=overrides + ([f"ckpt_path={last}"] if last.is_file() else []))
    train(base_cfg)


def check_base_checkpoint(folder: Path) -> None:
    """A finished base model's ``checkpoints/last.ckpt`` must hold the step its ``results.json`` reports:
    otherwise every job fine-tuned from it starts from other weights than the ones the base was tested with."""
    want = json.loads((folder / "results.json").read_text()).get("global_step")
    if want is not None:
        require_step(
            folder / "checkpoints" / "last.ckpt",
            int(want),
            f"{folder / 'results.json'} reports the base model trained to step {want}: the checkpoint is "
            f"stale (remove {folder} and run again)",
        )


def require_step(last: Path, want: int, why: str) -> None:
    """Refuse a ``last.ckpt`` (when there is one) that holds another step than ``want``, saying ``why``."""
    if not last.is_file():
        return
    step = int(read_checkpoint(last).get("global_step", -1))
    if step != want:
        raise CheckpointError(f"{last}: holds step {step}, but {why}")
