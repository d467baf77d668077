"""graf-train: fit the model when it has parameters, then test it; writes results.json."""

from __future__ import annotations

import logging
import time

from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from graf.cli.common import CONF_PATH, build, sweep_value, task_wrapper, test_and_report

log = logging.getLogger("graf")


@task_wrapper
def train(cfg: DictConfig) -> tuple[dict, dict]:
    started = time.perf_counter()
    objects = build(cfg)
    model, trainer = objects["model"], objects["trainer"]
    init_from = (cfg.get("finetune") or {}).get("init_from")
    if init_from:
        load_weights(model, init_from)
    if getattr(model, "has_trainable_parameters", True):
        # resumes from ckpt_path (e.g. <old run>/checkpoints/last.ckpt) when given
        trainer.fit(model=model, datamodule=objects["datamodule"], ckpt_path=cfg.get("ckpt_path"))
    else:
        log.info("%s has no trainable parameters: nothing to fit, testing directly", type(model).__name__)
    # the final weights are tested: there is no validation split to choose a checkpoint on
    metrics = test_and_report(cfg, objects, started, task="train")
    return metrics, objects


def load_weights(model, path) -> None:
    """Fine-tuning: copy a checkpoint's weights into ``model`` (strict), with a clear error when the file is
    missing or holds another architecture."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"finetune.init_from: {path} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)["state_dict"]
    except Exception as exc:
        raise ValueError(f"finetune.init_from: {path} is not a Lightning checkpoint ({exc})") from None
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0:3]
        raise ValueError(f"finetune.init_from: {path} holds weights of another architecture than "
                         f"{type(model).__name__} as configured: {' '.join(first)}") from None
    log.info("fine-tuning %s from the weights of %s", type(model).__name__, path)


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="train")
def main(cfg: DictConfig) -> float:
    metrics, _ = train(cfg)
    return sweep_value(cfg, metrics)


if __name__ == "__main__":
    main()
