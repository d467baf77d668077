"""graf-train: fit the model when it has parameters, then test it; writes results.json."""

from __future__ import annotations

import logging
import time

import hydra
from omegaconf import DictConfig

from graf.cli.common import CONF_PATH, build, sweep_value, task_wrapper, test_and_report
from graf.models.base import CheckpointError, check_checkpoint, read_checkpoint

log = logging.getLogger("graf")


@task_wrapper
def train(cfg: DictConfig) -> tuple[dict, dict]:
    started = time.perf_counter()
    objects = build(cfg)
    model, trainer = objects["model"], objects["trainer"]
    init_from = (cfg.get("finetune") or {}).get("init_from")
    if init_from:
        load_weights(model, init_from)
    if cfg.get("ckpt_path"):  # resume: refuse another class's or an old layout's checkpoint up front
        check_checkpoint(read_checkpoint(cfg.ckpt_path), type(model), cfg.ckpt_path)
    if getattr(model, "has_trainable_parameters", True):
        # resumes from ckpt_path (e.g. <old run>/checkpoints/last.ckpt) when given
        step0, t0 = trainer.global_step, time.perf_counter()
        trainer.fit(model=model, datamodule=objects["datamodule"], ckpt_path=cfg.get("ckpt_path"))
        fit_s, steps = time.perf_counter() - t0, max(0, trainer.global_step - step0)
        objects["timing"] = {"fit_s": round(fit_s, 3), "fit_steps": int(steps),
                             "fit_s_per_step": round(fit_s / steps, 4) if steps else None}
    else:
        log.info("%s has no trainable parameters: nothing to fit, testing directly", type(model).__name__)
    # the final weights are validated and tested (nothing is chosen on the test split)
    metrics = test_and_report(cfg, objects, started, task="train")
    return metrics, objects


def load_weights(model, path) -> None:
    """Fine-tuning: copy a checkpoint's weights into ``model`` (strict), with a clear error when the file is
    missing, was written by another class or layout, or holds another architecture."""
    ckpt = read_checkpoint(path)
    check_checkpoint(ckpt, type(model), path)
    try:
        model.load_state_dict(ckpt["state_dict"], strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0:3]
        raise CheckpointError(f"finetune.init_from: {path} holds weights of another architecture than "
                              f"{type(model).__name__} as configured: {' '.join(first)}") from None
    log.info("fine-tuning %s from the weights of %s", type(model).__name__, path)


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="train")
def main(cfg: DictConfig) -> float:
    metrics, _ = train(cfg)
    return sweep_value(cfg, metrics)


if __name__ == "__main__":
    main()
