"""graf-train: fit the model when it has parameters, then test it; writes results.json."""

from __future__ import annotations

import logging
import time

import hydra
from omegaconf import DictConfig

from graf.cli.common import CONF_DIR, build, sweep_value, task_wrapper, test_and_report

log = logging.getLogger("graf")


@task_wrapper
def train(cfg: DictConfig) -> tuple[dict, dict]:
    started = time.perf_counter()
    objects = build(cfg)
    model, trainer = objects["model"], objects["trainer"]
    if getattr(model, "has_trainable_parameters", True):
        # resumes from ckpt_path (e.g. <old run>/checkpoints/last.ckpt) when given
        trainer.fit(model=model, datamodule=objects["datamodule"], ckpt_path=cfg.get("ckpt_path"))
    else:
        log.info("%s has no trainable parameters: nothing to fit, testing directly", type(model).__name__)
    # the final weights are tested: there is no validation split to choose a checkpoint on
    metrics = test_and_report(cfg, objects, started, task="train")
    return metrics, objects


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="train")
def main(cfg: DictConfig) -> float:
    metrics, _ = train(cfg)
    return sweep_value(cfg, metrics)


if __name__ == "__main__":
    main()
