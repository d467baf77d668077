"""Stopping and resuming a training run: a resumed checkpoint checked against the run's settings
(:func:`check_resume`), and what a run stopped on purpose says and leaves: SIGTERM (a cluster's pre-emption,
:func:`preempted`: ``preempted.json``, exit code 143) or Ctrl+C (:func:`interrupted`: exit code 130), each with the
way to resume it; a Ctrl+C before or after training says what was kept (:func:`not_done`,
:func:`tested_after_training`).
"""

from __future__ import annotations

import logging
import shlex
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from graf.app.config import output_dir, override_key, run_settings
from graf.callbacks import Preemption
from graf.data.fingerprint import find_scene
from graf.errors import Preempted
from graf.interrupts import INTERRUPTED_EXIT_CODE
from graf.io import atomic_write_json, is_rank_zero
from graf.models.base import CheckpointError, check_checkpoint, read_checkpoint
from graf.run.evaluation import run_device
from graf.run.record import Resumed

log = logging.getLogger("graf")


class Interrupted(Exception):
    """Training stopped by Ctrl+C: the command prints where it stopped and how to resume, and exits with
    :attr:`exit_code`."""

    exit_code = INTERRUPTED_EXIT_CODE


def interrupted(cfg: DictConfig, trainer) -> Interrupted:
    """After a Ctrl+C stopped ``trainer.fit``: the :class:`Interrupted` to raise, saying at which step and epoch
    it stopped, the output folder, and the command that resumes it (from the checkpoint the
    :class:`graf.callbacks.Preemption` callback saved, else the newest one there is)."""
    ckpt = last_checkpoint(trainer)
    where = (
        f"interrupted (Ctrl+C): training stopped at step {int(trainer.global_step)} of {int(trainer.max_steps)} "
        f"(epoch {int(trainer.current_epoch)}); output folder: {output_dir(cfg)}"
    )
    if not ckpt:
        return Interrupted(f"{where}; no checkpoint was written: run the command again to start over")
    return Interrupted(f"{where}; checkpoint: {ckpt}\nresume with: {resume_command(ckpt)}")


def last_checkpoint(trainer) -> str | None:
    """The checkpoint the :class:`graf.callbacks.Preemption` callback saved at an interrupt, else the newest one the
    run wrote (None: none)."""
    pre = next((cb for cb in trainer.callbacks if isinstance(cb, Preemption)), None)
    ckpt = (pre.saved or {}).get("checkpoint") if pre else None
    if ckpt is None:
        ckpt = next(
            (cb.last_model_path for cb in trainer.checkpoint_callbacks if getattr(cb, "last_model_path", "")), None
        )
    return ckpt


def not_done(out: Path, aside: list[Path], what: str) -> str:
    """What a Ctrl+C before anything was finished leaves (``what``: ``nothing was trained``), for
    :func:`graf.interrupts.stage`: the output folder, where a finished run moved aside from it is kept, and what
    to do (the same command again)."""
    kept = f"; the finished run that was there is kept in {aside[0]}" if aside else ""
    return f"{what}; output folder: {out}{kept}; run the command again"


def tested_after_training(built, trained: bool) -> str:
    """What a Ctrl+C while graf-train tests leaves, for :func:`graf.interrupts.stage`: when it trained, the step
    and checkpoint training finished at and the command that tests them (the same command resuming that
    checkpoint, which trains nothing more); otherwise that nothing was written."""
    out, trainer = built.output_dir, built.trainer
    ckpt = last_checkpoint(trainer) if trained else None
    if not ckpt:
        return not_done(out, [], "results.json was not written")
    return (
        f"training had finished at step {int(trainer.global_step)} (checkpoint: {ckpt}); results.json was not "
        f"written; output folder: {out}\nto test it, resume with: {resume_command(ckpt)}"
    )


def resume_command(ckpt: str) -> str:
    """The command line that resumes this run from ``ckpt``: the command's own with ``ckpt_path=<ckpt>``
    (outside a command: that setting alone)."""
    if not HydraConfig.initialized():
        return f"ckpt_path={ckpt}"
    args = [a for a in sys.argv[1:] if override_key(a) != "ckpt_path"] + [f"ckpt_path={ckpt}"]
    return " ".join(shlex.quote(a) for a in [Path(sys.argv[0]).name, *args])


def preempted(cfg: DictConfig, trainer, step0: int, fit_s: float | None = None) -> Preempted:
    """After a SIGTERM stopped ``trainer.fit``: ``preempted.json`` in the output folder (the step, the checkpoint,
    the wall seconds the fit ran before the signal, the command's way to resume) and the :class:`Preempted` to
    raise."""
    saved = next((cb.saved for cb in trainer.callbacks if isinstance(cb, Preemption) and cb.saved), None)
    out = output_dir(cfg)
    record = {
        "preempted": "SIGTERM",
        "global_step": int(trainer.global_step),
        "start_step": int(step0),
        "max_steps": int(trainer.max_steps),
        "checkpoint": (saved or {}).get("checkpoint"),
        "fit_s": None if fit_s is None else round(float(fit_s), 3),
        # where this attempt trained: a curve point resumed elsewhere lists each attempt's device (graf-curves)
        "device": run_device(trainer, trainer.lightning_module),
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


def check_resume(cfg: DictConfig, model, dm, path) -> Resumed:
    """Resuming ``ckpt_path``: refuse another class's or an old layout's checkpoint, another architecture or
    model setting (``model.*`` but inference settings), other data, neighbor or seed settings, or other training
    scenes (by content) than the checkpoint's; other trainer settings (a longer ``max_steps``) are allowed and
    both are recorded (results.json ``resumed``)."""
    ckpt = read_checkpoint(path)
    check_checkpoint(ckpt, type(model), path)
    # in the current form (GRaF's: a checkpoint written before model/features, graf.models.graf.legacy)
    saved = type(model).upgrade_hparams(ckpt.get("hyper_parameters") or {})
    allowed = set(type(model).INFERENCE_SETTINGS)
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
    diff = dict_diff(then, now)
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
        for k, (a, b) in dict_diff((run_then.get("trainer") or {}), run_now["trainer"]).items()
    }
    if changed:
        log.info(
            "resuming %s with other trainer settings: %s",
            path,
            ", ".join(f"{k} {v['checkpoint']} -> {v['run']}" for k, v in changed.items()),
        )
    return Resumed(str(path), int(ckpt.get("global_step", 0)), run_then or None, changed)


def dict_diff(a, b, prefix: str = "") -> dict:
    """``{dotted key: (a value, b value)}`` where two plain configs differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = {}
        for k in sorted(set(a) | set(b)):
            out.update(dict_diff(a.get(k, "<unset>"), b.get(k, "<unset>"), f"{prefix}{k}."))
        return out
    return {} if a == b else {prefix[:-1]: (a, b)}
