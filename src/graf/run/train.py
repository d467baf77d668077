"""graf-train's task: fit the model when it has parameters, then test it; writes results.json.

Fine-tuning (``conf/finetune``): ``finetune.init_from=CKPT`` starts from a checkpoint's weights with a fresh
optimiser and schedule, ``finetune.max_steps`` steps at ``finetune.lr``, on the measured fraction of the
run's scenes (``finetune=f05 ... f100``); with ``finetune=none`` the checkpoint is tested zero-shot (no step
trained).  ``finetune.base`` trains the checkpoint first when it is missing (studies).

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

from lightning.pytorch.callbacks import Timer
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf, open_dict

from graf.errors import ConfigError, Preempted
from graf.io import atomic_write_json, is_rank_zero
from graf.models.base import CheckpointError, check_checkpoint, read_checkpoint
from graf.run.build import build
from graf.run.config import (
    Results,
    expand_heldout,
    family,
    output_dir,
    override_key,
    run_settings,
    scene_configs,
    task_wrapper,
)
from graf.run.evaluation import test_and_report

log = logging.getLogger("graf")


@task_wrapper
def train(cfg: DictConfig) -> Results:
    """Fit the model when it has parameters (or fine-tune, or nothing for a zero-shot test), then validate and
    test it beside its baselines and write ``results.json``."""
    started = time.perf_counter()
    out = output_dir(cfg)
    if cfg.get("skip_finished"):
        done = finished_result(out)
        if done is not None:
            log.info("%s: finished before (%s); not run again", out, done.get("skipped") or "results.json")
            return Results(done.get("metrics", {}), {"output_dir": out, "finished_before": True})
    reason = skip_reason(cfg)
    if reason:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(out / "skipped.json", {"skipped": reason})
        log.info("%s: skipped: %s", out, reason)
        return Results({}, {"output_dir": out, "skipped": reason})
    cfg = expand_heldout(resolve_base(cfg))
    ft = cfg.get("finetune") or {}
    if ft and OmegaConf.is_missing(ft, "init_from"):
        raise ConfigError(
            f"finetune={_choice(cfg, 'finetune')} fine-tunes a checkpoint: set finetune.init_from=CKPT "
            "(e.g. <run>/checkpoints/last.ckpt), or finetune.init_from=null to train from scratch on "
            "the fraction"
        )
    if ft.get("init_from"):
        ensure_base(cfg)
        cfg = finetune_config(cfg)
    check_training_length(cfg)
    init_from = ft.get("init_from")
    zero_shot = bool(init_from) and ft.get("fraction") is None  # finetune=none
    objects = build(cfg, trains=not zero_shot)
    model, trainer = objects["model"], objects["trainer"]
    if init_from:
        load_weights(model, init_from)
    resumed = None
    if cfg.get("ckpt_path"):  # resume: refuse another class's, an old layout's or other settings' checkpoint up front
        resumed = check_resume(cfg, model, objects["datamodule"], cfg.ckpt_path)
        objects["resumed"] = resumed
    if zero_shot:
        log.info("finetune=none: testing %s zero-shot (no step trained)", init_from)
    elif getattr(model, "has_trainable_parameters", True):
        # resumes from ckpt_path (e.g. <old run>/checkpoints/last.ckpt) when given
        step0, t0 = (resumed or {}).get("global_step", 0), time.perf_counter()
        try:
            trainer.fit(model=model, datamodule=objects["datamodule"], ckpt_path=cfg.get("ckpt_path"))
        except SIGTERMException:
            raise preempted(cfg, trainer, step0, time.perf_counter() - t0) from None
        fit_s, steps = time.perf_counter() - t0, max(0, trainer.global_step - step0)
        check_last_checkpoint(trainer, out)
        objects["timing"] = {
            "fit_s": round(fit_s, 3),
            "fit_steps": int(steps),
            "fit_s_per_step": round(fit_s / steps, 4) if steps else None,
        }
        objects["training"] = training_record(trainer, step0)
    else:
        log.info("%s has no trainable parameters: nothing to fit, testing directly", type(model).__name__)
    if init_from:
        dm, start = objects["datamodule"], read_checkpoint(init_from)
        objects["finetune"] = {
            "init_from": str(init_from),
            "mode": "zero-shot" if zero_shot else "fine-tune",
            "fraction": ft.get("fraction"),
            "seed": int(ft.get("seed") or 0),
            "test_pool": dm.test_pool,
            "n_measured": int(len(dm.measured_rows)),
            "n_train": dm.n_train,
            "steps": 0 if zero_shot else int(objects.get("timing", {}).get("fit_steps", 0)),
            "lr": ft.get("lr"),
            "base_steps": int(start.get("global_step", 0)),
            "base_scenes": (start.get("graf") or {}).get("scenes"),
        }
    # the final weights are validated and tested (nothing is chosen on the test split)
    metrics = test_and_report(cfg, objects, started, task="train")
    return Results(metrics, objects)


def check_last_checkpoint(trainer, out: Path) -> None:
    """After a finished fit: the ``last.ckpt`` that every reader opens (fine-tuning from a study's base,
    graf-curves' next point, a search's best trial) must hold the weights training ended with.  Refuse, naming
    the files, when it holds another step (e.g. a pre-emption's checkpoint left behind while the final weights
    went to a versioned copy); a finished run's stale ``preempted.json`` is removed."""
    for cb in getattr(trainer, "checkpoint_callbacks", []):
        if not getattr(cb, "save_last", False) or not getattr(cb, "dirpath", None):
            continue
        require_step(
            Path(cb.dirpath) / "last.ckpt",
            int(trainer.global_step),
            f"training ended at step {int(trainer.global_step)} (its final weights are in "
            f"{cb.last_model_path or 'no file'}); readers of last.ckpt would get stale weights: keep "
            "callbacks.model_checkpoint.enable_version_counter=false",
        )
    stale = out / "preempted.json"
    if stale.is_file():
        log.info("%s: the pre-empted run has finished; removing its preempted.json", out)
        stale.unlink()


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


def training_record(trainer, step0: int) -> dict:
    """What results.json records of the training length (``training``): the steps asked and reached, and why
    training stopped before ``max_steps`` when it did.  A stop that is not the user's own limit
    (``trainer.max_epochs``, ``trainer.max_time``) is warned about loudly."""
    asked, epochs = int(trainer.max_steps), int(trainer.max_epochs if trainer.max_epochs is not None else -1)
    reached = int(trainer.global_step)
    rec = {
        "max_steps": asked,
        "max_epochs": epochs,
        "start_step": int(step0),
        "global_step": reached,
        "steps_trained": reached - int(step0),
        "epochs_trained": int(trainer.current_epoch),
        "stopped_early": False,
        "world_size": int(trainer.world_size),
    }
    from graf.callbacks import TargetCount

    counted = next((cb for cb in trainer.callbacks if isinstance(cb, TargetCount) and cb.targets is not None), None)
    if counted is not None:  # measured, over every rank: batch_size x world_size per step
        rec["targets_seen"] = counted.targets
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
        rec.update(stopped_early=True, stop_reason=reason, own_limit=own)
        msg = f"training stopped at step {reached} of trainer.max_steps={asked}: {reason}"
        if own:
            log.info(msg)
        else:
            log.warning("WARNING: %s; results.json records it under 'training'", msg)
            print(f"WARNING: {msg}", file=sys.stderr)
    return rec


def preempted(cfg: DictConfig, trainer, step0: int, fit_s: float | None = None) -> Preempted:
    """After a SIGTERM stopped ``trainer.fit``: ``preempted.json`` in the output folder (the step, the checkpoint,
    the wall seconds the fit ran before the signal, the command's way to resume) and the :class:`Preempted` to
    raise."""
    from graf.callbacks import Preemption

    saved = next((cb.saved for cb in trainer.callbacks if isinstance(cb, Preemption) and cb.saved), None)
    out = output_dir(cfg)
    record = {
        "preempted": "SIGTERM",
        "global_step": int(trainer.global_step),
        "start_step": int(step0),
        "max_steps": int(trainer.max_steps),
        "checkpoint": (saved or {}).get("checkpoint"),
        "fit_s": None if fit_s is None else round(float(fit_s), 3),
    }
    if saved:
        msg = (
            f"SIGTERM: training stopped at step {saved['global_step']} of {int(trainer.max_steps)}; checkpoint saved "
            f"to {saved['checkpoint']}; resume with the same command and ckpt_path={saved['checkpoint']}"
        )
    elif not any(isinstance(cb, Preemption) for cb in trainer.callbacks):
        msg = (
            f"SIGTERM: training stopped at step {int(trainer.global_step)} with no checkpoint saved (this run's "
            "callbacks have no pre-emption callback, graf.callbacks.Preemption)"
        )
    else:  # the signal came between training steps (during a validation): the last checkpoint is what there is
        last = next(
            (cb.last_model_path for cb in trainer.checkpoint_callbacks if getattr(cb, "last_model_path", "")), None
        )
        msg = (
            f"SIGTERM: stopped at step {int(trainer.global_step)} of {int(trainer.max_steps)} outside a training "
            f"step (during validation); "
            + (f"resume with the same command and ckpt_path={last}" if last else "no checkpoint was written")
        )
        record["checkpoint"] = last
    if is_rank_zero():
        atomic_write_json(out / "preempted.json", record)
    return Preempted(msg)


# settings whose change between a checkpoint and the run resuming it changes what is trained: refused
RESUME_FIXED = ("data", "neighbors", "seed")


def check_resume(cfg: DictConfig, model, dm, path) -> dict:
    """Resuming ``ckpt_path``: refuse another class's or an old layout's checkpoint, another architecture or
    model setting (``model.*`` but inference settings), other data, neighbor or seed settings, or other training
    scenes (by content) than the checkpoint's; other trainer settings (a longer ``max_steps``) are allowed and
    both are recorded (results.json ``resumed``)."""
    from graf.data.fingerprint import find_scene

    ckpt = read_checkpoint(path)
    check_checkpoint(ckpt, type(model), path)
    saved = dict(ckpt.get("hyper_parameters") or {})
    allowed = set(getattr(type(model), "INFERENCE_SETTINGS", ()))
    info = ckpt.get("graf") or {}
    run_then, run_now = info.get("run") or {}, run_settings(cfg)
    then = {
        "model": {k: v for k, v in saved.items() if k not in allowed},
        **({g: run_then.get(g) for g in RESUME_FIXED} if run_then else {}),
    }
    now = {
        "model": {k: v for k, v in dict(model.hparams).items() if k not in allowed},
        **({g: run_now.get(g) for g in RESUME_FIXED} if run_then else {}),
    }
    diff = _dict_diff(then, now)
    if diff:
        raise CheckpointError(
            f"ckpt_path={path}: resuming with other settings than it was trained with: "
            + "; ".join(f"{k}: checkpoint {a!r}, this run {b!r}" for k, (a, b) in diff.items())
            + ". They change what is trained: resume with the checkpoint's settings (or start from its weights with "
            "finetune.init_from=)"
        )
    trained = info.get("scenes") or {}
    if trained and any(fp.get("digest") for fp in (v.get("fingerprint") or {} for v in trained.values())):
        other = [d.name for d, fp in zip(dm.sets, dm.fingerprints()) if find_scene(trained, d.name, fp) is None]
        if other:
            raise CheckpointError(
                f"ckpt_path={path}: was trained on {', '.join(sorted(trained))}, not on the content "
                f"of this run's scene(s) {', '.join(other)}: resume on the same data"
            )
    changed = {
        f"trainer.{k}": {"checkpoint": a, "run": b}
        for k, (a, b) in _dict_diff((run_then.get("trainer") or {}), run_now["trainer"]).items()
    }
    if changed:
        log.info(
            "resuming %s with other trainer settings: %s",
            path,
            ", ".join(f"{k} {v['checkpoint']} -> {v['run']}" for k, v in changed.items()),
        )
    return {
        "checkpoint": str(path),
        "global_step": int(ckpt.get("global_step", 0)),
        "checkpoint_settings": run_then or None,
        "changed": changed,
    }


def _dict_diff(a, b, prefix: str = "") -> dict:
    """``{dotted key: (a value, b value)}`` where two plain configs differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = {}
        for k in sorted(set(a) | set(b)):
            out.update(_dict_diff(a.get(k, "<unset>"), b.get(k, "<unset>"), f"{prefix}{k}."))
        return out
    return {} if a == b else {prefix[:-1]: (a, b)}


def _choice(cfg: DictConfig, group: str) -> str:
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return str(HydraConfig.get().runtime.choices.get(group))
    return "..."


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
    """Why a study job is not run (None: it is).  ``same_family_only``: a job whose test scenes are of no
    training scene's layout family (conference_v1 -> office_v2).  ``finetune.base.band=scene`` (start from a model
    trained at
    the new scene's own band) differs from the run's band only for a scene with a fixed band (measured data:
    rfid_s23 at 915 MHz); for a simulated scene it would repeat the job with the run's band."""
    if cfg.get("same_family_only"):
        train = {family(str(c.get("name"))) for c in scene_configs(cfg.get("scene"))}
        test = {family(str(c.get("name"))) for c in scene_configs(cfg.get("eval_scene"))}
        if test and not test & train:
            return (
                f"same_family_only: test scenes of family {', '.join(sorted(test))}, training scenes of "
                f"{', '.join(sorted(train))}"
            )
    base = (cfg.get("finetune") or {}).get("base") or {}
    if base.get("band") != "scene":
        return None
    scenes = scene_configs(cfg.get("scene"))
    if not any(s.get("fixed_band") for s in scenes):
        return "finetune.base.band=scene on a scene simulated at any band: the same job as the one with the run's band"
    return None


def resolve_base(cfg: DictConfig) -> DictConfig:
    """With ``finetune.base``: the base run's folder (``base.dir``, or ``base.dir/<band>`` when ``base.band``
    names one; ``scene``: the band of the run's scene, e.g. 915mhz for rfid_s23) as ``finetune.base.folder``,
    and ``finetune.init_from=base`` (or null) as its last checkpoint."""
    base = (cfg.get("finetune") or {}).get("base")
    if not base or not base.get("dir"):
        if (cfg.get("finetune") or {}).get("init_from") == "base":
            raise ConfigError("finetune.init_from=base needs finetune.base (dir, overrides): the run to train first")
        return cfg
    band = base.get("band")
    if band == "scene":
        scenes = scene_configs(cfg.get("scene"))
        band = scenes[0].get("band") if scenes else None
        if not band:
            raise ConfigError("finetune.base.band=scene: the run's scene names no band of its own")
    folder = Path(str(base.dir)) / str(band) if band else Path(str(base.dir))
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.finetune.base.folder = str(folder)
        cfg.finetune.base.band_name = band
        if cfg.finetune.get("init_from") in (None, "base"):
            cfg.finetune.init_from = str(folder / "checkpoints" / "last.ckpt")
    return cfg


def finetune_config(cfg: DictConfig) -> DictConfig:
    """The run's config with the fine-tuning steps and learning rate applied (``trainer.max_steps``,
    ``model.lr``); a zero-shot run (``finetune=none``) trains nothing, so neither applies."""
    ft = cfg.finetune
    if ft.get("fraction") is None:
        return cfg
    cfg = cfg.copy()
    with open_dict(cfg):
        if ft.get("max_steps") is not None:
            cfg.trainer.max_steps = int(ft.max_steps)
            cfg.trainer.max_epochs = -1
        if ft.get("lr") is not None:
            if "lr" not in cfg.model:
                raise ConfigError(f"finetune.lr={ft.lr}: model {cfg.model._target_} has no lr setting")
            cfg.model.lr = float(ft.lr)
    return cfg


# command-line settings of a study job that describe the job itself, not the base model it starts from
JOB_SPECIFIC = (
    "experiment",
    "model",
    "scene",
    "eval_scene",
    "eval_band",
    "band",
    "neighbors",
    "finetune",
    "hydra",
    "skip_finished",
    "ckpt_path",
    "paths",
)


def job_overrides() -> list[str]:
    """The command-line settings of the running Hydra job that a base model shares (budgets, data_root,
    sim_num_tx, seed, trainer, ...): all but the job-specific ones (``JOB_SPECIFIC``)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    out = []
    for o in HydraConfig.get().overrides.task:
        key = override_key(o)
        if not any(key == k or key.startswith(k + ".") for k in JOB_SPECIFIC):
            out.append(o)
    return out


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
    from hydra import compose

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


def load_weights(model, path) -> None:
    """Fine-tuning: copy a checkpoint's weights into ``model`` (strict), with a clear error when the file is
    missing, was written by another class or layout, or holds another architecture."""
    ckpt = read_checkpoint(path)
    check_checkpoint(ckpt, type(model), path)
    saved = ckpt.get("hyper_parameters") or {}
    want = getattr(model, "hparams", {}).get("use_scene_index")
    if "use_scene_index" in saved and want is not None and bool(saved["use_scene_index"]) != bool(want):
        raise CheckpointError(
            f"finetune.init_from: {path} was trained with use_scene_index={saved['use_scene_index']} "
            f"({'4' if saved['use_scene_index'] else '3'}-D positions), but this run's model has "
            f"use_scene_index={want}: set model.use_scene_index={saved['use_scene_index']}"
        )
    try:
        model.load_state_dict(ckpt["state_dict"], strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0:3]
        raise CheckpointError(
            f"finetune.init_from: {path} holds weights of another architecture than "
            f"{type(model).__name__} as configured: {' '.join(first)}"
        ) from None
    model.scene_table = {**dict((ckpt.get("graf") or {}).get("scenes") or {}), **getattr(model, "scene_table", {})}
    log.info("fine-tuning %s from the weights of %s", type(model).__name__, path)
