"""graf-eval's task: validate and test a method (or a checkpoint, ckpt_path=...) on a scene; writes results.json.

With ``ckpt_path`` the model that runs is the checkpoint's: its class (recorded in the checkpoint; ``model=``
is not needed, and one naming another class is refused) with its own hyperparameters.  A ``model.*``
override on the command line is applied when it is an inference setting of that class
(``INFERENCE_SETTINGS``, e.g. ``model.chunk_rays``) and refused otherwise, since it would describe a model
that did not run; ``results.json`` records the checkpoint's hyperparameters (with the applied overrides)
as ``config.model`` and the checkpoint itself under ``checkpoint``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf, open_dict

from graf.app.config import CONF_DIR, check_run_settings, output_dir, override_key, task_wrapper, with_baselines_switch
from graf.app.spec import RunSpec
from graf.interrupts import stage
from graf.models.base import CheckpointError, check_checkpoint, checkpoint_class, read_checkpoint, safe_loading
from graf.plugins import CONF_DIRS
from graf.run.build import build
from graf.run.record import CheckpointInfo, Results, RunFacts
from graf.run.resume import not_done
from graf.run.writer import set_aside_finished, test_and_report


def model_overrides(overrides: Sequence[str]) -> tuple[str | None, list[str]]:
    """``(model group choice or None, [keys overridden under model.])`` from command-line overrides."""
    choice, keys = None, []
    for o in overrides:
        key = override_key(o)
        if key == "model":
            choice = o.split("=", 1)[1]
        elif key.startswith(("model.", "model/")):  # model/features=X: a nested group's choice (GRaF's)
            keys.append(key[len("model.") :].split("@")[0].replace("/", "."))
    return choice, keys


def load_checkpoint_model(cfg: DictConfig, path: str, overrides: Sequence[str]) -> tuple:
    """The checkpoint's model with the allowed ``model.*`` overrides applied, its config (the run's
    ``config.model``) and what results.json records of the checkpoint."""
    ckpt = read_checkpoint(path)
    choice, keys = model_overrides(overrides)
    target = (ckpt.get("graf") or {}).get("target")
    if target is None:  # written before checkpoints named their class: trust model=..., check the layout
        target = cfg.model._target_
    elif choice is not None and get_class(cfg.model._target_) is not checkpoint_class(target, path):
        raise CheckpointError(
            f"{path}: holds a {target} checkpoint, but model={choice} is {cfg.model._target_}; "
            "drop model=... (graf-eval takes the class from the checkpoint)"
        )
    cls = checkpoint_class(target, path)
    check_checkpoint(ckpt, cls, path)
    saved = dict(ckpt.get("hyper_parameters") or {})
    allowed = tuple(cls.INFERENCE_SETTINGS)
    # nested settings (model.features.pixel_window) too, an old checkpoint's in the current form
    trained = OmegaConf.create(cls.upgrade_hparams(saved))
    applied = {}
    for key in keys:
        value = OmegaConf.select(cfg.model, key)
        was = OmegaConf.select(trained, key, default=f"<not a setting of {cls.__name__}>")
        if key in allowed:
            applied[key] = value
        elif was != value:
            raise CheckpointError(
                f"model.{key}={value} cannot change the trained checkpoint {path} (it was trained with "
                f"{key}={was}); only inference settings "
                f"may be overridden at evaluation: {', '.join('model.' + a for a in allowed) or 'none'}"
            )
    with safe_loading():
        model = cls.load_from_checkpoint(path, map_location="cpu", weights_only=True, **applied)
    ran = OmegaConf.create({"_target_": target, **{k: v for k, v in dict(model.hparams).items()}})
    layout = int((ckpt.get("graf") or {}).get("layout", 1))
    info = CheckpointInfo(str(path), int(ckpt.get("global_step", 0)), target, layout, saved, applied)
    return model, ran, info


@task_wrapper
def evaluate(cfg: DictConfig, overrides: Sequence[str] | None = None) -> Results:
    """``overrides``: the command line's overrides (taken from Hydra when run as a command)."""
    started = time.perf_counter()
    cfg, out, aside = with_baselines_switch(cfg), output_dir(cfg), []
    with stage("set-up", lambda: not_done(out, aside, "nothing was tested")):
        check_run_settings(cfg)  # before a finished run's files are moved aside
        aside += [p for p in [set_aside_finished(out, [cfg.get("ckpt_path")])] if p]
        built = build(RunSpec.of(cfg), trains=False)
        checkpoint = None
        if cfg.get("ckpt_path"):
            if overrides is None:
                overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
            model, ran, checkpoint = load_checkpoint_model(built.cfg, cfg.ckpt_path, overrides)
            run_cfg = built.cfg.copy()
            with open_dict(run_cfg):  # the model that runs is the checkpoint's: the config records it
                run_cfg.model = ran
            built = dataclasses.replace(built, model=model, cfg=run_cfg)
    with stage("testing", lambda: not_done(out, aside, "results.json was not written")):
        return Results(*test_and_report(built.cfg, built, RunFacts("eval", started, checkpoint=checkpoint)))


def checkpoint_model_choice(args: Sequence[str]) -> str | None:
    """``model=<option>`` to add to a command line that tests a checkpoint (``ckpt_path=``) and overrides a
    ``model.*`` key without naming ``model=``: the model config of the checkpoint's class, so that the key
    exists when Hydra composes (the default model, KNN, has no ``lr``) and :func:`load_checkpoint_model` can
    apply or refuse it.  None when nothing is to be added (or the checkpoint cannot be read: the run then
    reports that itself)."""
    if not any(a.startswith("ckpt_path=") for a in args) or any(override_key(a) == "model" for a in args):
        return None
    if not any(override_key(a).startswith(("model.", "model/")) for a in args):
        return None
    path = next(a.split("=", 1)[1] for a in args if a.startswith("ckpt_path="))
    try:
        target = (read_checkpoint(path).get("graf") or {}).get("target")
        cls = checkpoint_class(target, path) if target else None
    except Exception:
        return None
    if cls is None:
        return None
    folders = [CONF_DIR, *CONF_DIRS]  # graf's own, then the plugins' (graf.plugins.add_conf)
    for f in [f for d in folders for f in sorted((d / "model").glob("*.yaml"))]:  # graf before graf_cpu: the base
        t = OmegaConf.load(f).get("_target_")
        try:
            if t and get_class(str(t)) is cls:
                return f.stem
        except Exception:
            continue
    return None
