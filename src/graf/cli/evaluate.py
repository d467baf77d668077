"""graf-eval: test a method (or a checkpoint, ckpt_path=...) on a scene; writes results.json."""

from __future__ import annotations

import time

import hydra
from omegaconf import DictConfig

from graf.cli.common import CONF_PATH, build, sweep_value, task_wrapper, test_and_report


@task_wrapper
def evaluate(cfg: DictConfig) -> tuple[dict, dict]:
    started = time.perf_counter()
    objects = build(cfg)
    if cfg.get("ckpt_path"):
        objects["model"] = type(objects["model"]).load_from_checkpoint(cfg.ckpt_path, map_location="cpu")
    metrics = test_and_report(cfg, objects, started, task="eval")
    return metrics, objects


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="eval")
def main(cfg: DictConfig) -> float:
    metrics, _ = evaluate(cfg)
    return sweep_value(cfg, metrics)


if __name__ == "__main__":
    main()
