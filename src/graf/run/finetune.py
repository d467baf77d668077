"""Fine-tuning (``conf/finetune``): ``finetune.init_from=CKPT`` starts from a checkpoint's weights with a fresh
optimiser and schedule, ``finetune.max_steps`` steps at ``finetune.lr``, on the measured fraction of the
run's scenes (``finetune=f05 ... f100``); with ``finetune=none`` the checkpoint is tested zero-shot (no step
trained).  ``finetune.base`` names a base run to train first when it is missing (studies: :func:`resolve_base`;
graf-train trains it).
"""

from __future__ import annotations

import logging
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from graf.app.config import override_key
from graf.app.spec import RunSpec
from graf.errors import ConfigError
from graf.models.base import CheckpointError, check_checkpoint, read_checkpoint
from graf.run.record import Finetune

log = logging.getLogger("graf")


def check_finetune(cfg: DictConfig) -> None:
    """A fine-tuning option (``finetune=f05 ...``) needs the checkpoint it fine-tunes."""
    ft = cfg.get("finetune") or {}
    if ft and OmegaConf.is_missing(ft, "init_from"):
        raise ConfigError(
            f"finetune={group_choice(cfg, 'finetune')} fine-tunes a checkpoint: set finetune.init_from=CKPT "
            "(e.g. <run>/checkpoints/last.ckpt), or finetune.init_from=null to train from scratch on "
            "the fraction"
        )


def finetune_record(cfg: DictConfig, dm, steps: int) -> Finetune:
    """What results.json records of a run that started from ``finetune.init_from`` (``steps``: trained since)."""
    ft = cfg.finetune
    zero_shot = ft.get("fraction") is None
    start = read_checkpoint(ft.init_from)
    return Finetune(
        init_from=str(ft.init_from),
        mode="zero-shot" if zero_shot else "fine-tune",
        fraction=ft.get("fraction"),
        seed=int(ft.get("seed") or 0),
        test_pool=dm.test_pool,
        n_measured=int(len(dm.measured_rows)),
        n_train=dm.n_train,
        steps=0 if zero_shot else int(steps),
        lr=ft.get("lr"),
        base_steps=int(start.get("global_step", 0)),
        base_scenes=(start.get("graf") or {}).get("scenes"),
    )


def group_choice(cfg: DictConfig, group: str) -> str:
    if HydraConfig.initialized():
        return str(HydraConfig.get().runtime.choices.get(group))
    return "..."


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
        scenes = RunSpec.of(cfg).scenes
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
    if not HydraConfig.initialized():
        return []
    out = []
    for o in HydraConfig.get().overrides.task:
        key = override_key(o)
        if not any(key == k or key.startswith(k + ".") for k in JOB_SPECIFIC):
            out.append(o)
    return out


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
