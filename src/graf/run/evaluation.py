"""Testing a built run: validation and test of the final weights, neighbor reliance (the same figures with
each target's neighbors swapped for another target's) and the baselines beside the model on the same data; the
run's record is made of them, written and printed by :mod:`graf.run.writer`.

Every command writes ``results.json`` into its output folder (:class:`graf.run.record.RunRecord`)::

    {"method", "scene", "band_hz", "n_train", "n_test",
     "metrics": {"val/mse", ..., "test/mse", "test/psnr", "test/ssim", "test/lpips", "test/reliance_db"},
     "seconds", "config", "splits", "ray_sampling", ...}

and, with ``save_predictions=true``, ``predictions.npz`` (``pred``, ``target``: float32 [N, 90, 360] in
[0, 1]; ``ids``: int [N]).  A figure of predicted vs true spectra (``spectra.png``) goes beside them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from graf.callbacks import PredictionCollector
from graf.metrics.names import record_order
from graf.run.build import BuiltRun, EvalScene, evaluation_trainer
from graf.run.record import BaselineFigures, RunResult, Timing
from graf.search.objectives import objective_values

log = logging.getLogger("graf")


class ModelEvaluation(NamedTuple):
    """A model's validation and test figures (``{val/..., test/...}``), its test predictions and the seconds each
    pass took."""

    metrics: dict
    arrays: dict[str, np.ndarray]
    timing: Timing


def evaluate_model(cfg: DictConfig, model, dm, loggers=()) -> ModelEvaluation:
    """Validation then test of ``model``.  ``validate=false`` (studies, which choose nothing) skips validation:
    the ``val/...`` figures are then None; ``test=false`` (the trials of a hyperparameter search, which must not
    see the test split) skips the test: the ``test/...`` figures are then None."""
    collector = PredictionCollector()
    trainer = evaluation_trainer(cfg, loggers, [collector])
    t0 = time.perf_counter()
    metrics = {}
    if cfg.get("validate", True):
        interruptible(trainer, trainer.validate, model=model, datamodule=dm, verbose=False)
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
    t1 = time.perf_counter()
    if cfg.get("test", True):
        interruptible(trainer, trainer.test, model=model, datamodule=dm, verbose=False)
        metrics.update({k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")})
    t2 = time.perf_counter()
    if cfg.get("reliance", True) and model.uses_neighbors:
        metrics.update(reliance_figures(cfg, model, dm, metrics, trainer))
    timing = Timing(val_s=round(t1 - t0, 3), test_s=round(t2 - t1, 3), reliance_s=round(time.perf_counter() - t2, 3))
    return ModelEvaluation(record_order(metrics), collector.arrays(), timing)


def interruptible(trainer, run, **kwargs):
    """``trainer.validate`` or ``trainer.test`` (``run``); a Ctrl+C, which Lightning turns into exit code 1 with
    nothing said, is raised on as the KeyboardInterrupt it was (the command then says where it stopped)."""
    try:
        return run(**kwargs)
    except SystemExit:
        if trainer.interrupted:
            raise KeyboardInterrupt from None
        raise


def reliance_figures(cfg: DictConfig, model, dm, metrics: dict, trainer) -> dict:
    """``{split}/psnr_swapped`` and ``{split}/reliance_db`` of each split evaluated (logged beside the split's
    other figures, csv and wandb)."""
    out = {}
    for split, done in (("val", cfg.get("validate", True)), ("test", cfg.get("test", True))):
        swapped = swapped_psnr(cfg, model, dm, split) if done else None
        if swapped is None or metrics.get(f"{split}/psnr") is None:
            continue
        figures = {f"{split}/psnr_swapped": swapped, f"{split}/reliance_db": metrics[f"{split}/psnr"] - swapped}
        out.update(figures)
        for lg in trainer.loggers:
            lg.log_metrics(figures, step=trainer.global_step)
            lg.save()
    return out


def run_device(trainer, model) -> str:
    """The device the run trained and evaluated on, e.g. ``cuda:0 (NVIDIA H200)`` or ``cpu``.

    From the trainer's strategy, not the module: Lightning moves the module back to the CPU when a fit or test
    ends, so ``model.device`` read afterwards says ``cpu`` for a run that ran on a GPU."""
    dev = getattr(getattr(trainer, "strategy", None), "root_device", None)
    dev = torch.device(dev) if dev is not None else model.device
    if dev.type == "cuda" and torch.cuda.is_available():
        return f"{dev} ({torch.cuda.get_device_name(dev)})"
    return str(dev)


def short_device(device: str | None) -> str | None:
    """``cpu``, or the card's name for a GPU run (``cuda:0 (NVIDIA H200)`` -> ``NVIDIA H200``)."""
    if not device:
        return None
    if "(" in device and device.endswith(")"):
        return device[device.index("(") + 1 : -1]
    return device


def swapped_psnr(cfg: DictConfig, model, dm, split: str = "test") -> float | None:
    """Neighbor reliance's second pass: the ``split`` (test or val) PSNR with each target's neighbors "
    "replaced by another
    target's of the same scene (a derangement seeded by ``reliance_seed``; the same L, positions and spectra of
    real neighbors, only the wrong ones).  A model that reads its neighbors loses PSNR; one that ignores them
    scores the same.  None when a scene has a single target in the split."""
    seed = int(cfg.get("reliance_seed") or 0)
    if dm.swapped_neighbors(dm.eval_split if split == "test" else "val", seed) is None:
        return None
    trainer = evaluation_trainer(cfg)
    dm.swap_seed = seed
    try:
        (trainer.test if split == "test" else trainer.validate)(model=model, datamodule=dm, verbose=False)
    finally:
        dm.swap_seed = None
    return float(trainer.callback_metrics[f"{split}/psnr"])


@dataclass(eq=False)
class BaselineResult:
    """A baseline (nothing trained) tested on a run's test scene: its figures and test predictions."""

    method: str
    scene: str
    n_test: int
    trainable_parameters: int
    metrics: dict
    seconds: float
    arrays: dict[str, np.ndarray]

    def figures(self) -> BaselineFigures:
        return BaselineFigures(self.metrics, self.seconds, self.trainable_parameters)


def test_baseline(cfg: DictConfig, name: str, bcfg: DictConfig, dm) -> BaselineResult:
    """Validate and test a baseline (nothing trained) on the same datamodule, neighbors and splits."""
    started = time.perf_counter()
    model = hydra.utils.instantiate(bcfg)
    metrics, arrays, _ = evaluate_model(cfg, model, dm)
    return BaselineResult(
        method=model.method,
        scene=dm.scene_name,
        n_test=int(len(arrays["ids"])),
        trainable_parameters=int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
        metrics=metrics,
        seconds=round(time.perf_counter() - started, 3),
        arrays=arrays,
    )


@dataclass(eq=False)
class SceneTest:
    """One test scene of a run: the model's evaluation (its timing with the fit's) and its baselines'."""

    scene: EvalScene
    model: ModelEvaluation
    baselines: list[BaselineResult]


def evaluate_scenes(cfg: DictConfig, built: BuiltRun, fit: Timing) -> list[SceneTest]:
    """Every test scene on its own (the first one's figures are the run's headline; its evaluation alone is logged):
    the model, then the baselines on the same data (a baseline equal to the model is skipped)."""
    baselines = [(name, bcfg) for name, bcfg in selected_baselines(cfg).items() if bcfg != cfg.model]
    done = []
    for ev in built.evaluations:
        m = evaluate_model(cfg, built.model, ev.datamodule, built.loggers if not done else ())
        timing = dataclasses.replace(fit, val_s=m.timing.val_s, test_s=m.timing.test_s, reliance_s=m.timing.reliance_s)
        done.append(
            SceneTest(
                ev,
                m._replace(timing=timing),
                [test_baseline(cfg, name, bcfg, ev.datamodule) for name, bcfg in baselines],
            )
        )
    return done


def ray_sampling(model, dm) -> dict | None:
    """Samples per ray and the effective voxel (sample spacing) of a ray-rendering model on each of the
    datamodule's scenes; logs a warning where ``max_samples`` caps S (voxels longer than nominal)."""
    out = {}
    for k, d in enumerate(dm.sets):
        geometry = {
            "ray_length": dm.ray_length[k : k + 1],
            "wavelength": dm.wavelength[k : k + 1],
            "gw_pos": dm.gw_pos[k : k + 1],
            "gw_rot": dm.gw_rot[k : k + 1],
            "bounds": dm.bounds[k : k + 1],
            "scene_index": dm.scene_index[k : k + 1],
        }
        r = model.ray_sampling(geometry)
        if r is None:
            return None
        out[d.name] = r
        if r["capped"]:
            log.warning(
                "%s on %s: max_samples caps the samples per ray at %d (%d needed), so each sample spans "
                "%.2f wavelengths (%.3f m) instead of %.2f",
                type(model).__name__,
                d.name,
                r["samples_per_ray"],
                r["uncapped_samples"],
                r["sample_spacing_wavelengths"],
                r["sample_spacing_m"],
                r["nominal_spacing_wavelengths"],
            )
    return out


def selected_baselines(cfg: DictConfig) -> dict:
    """The baselines to test beside the model (``{name: model config}``); ``baselines=null`` and ``baselines={}``
    switch them off (on the command line, :func:`graf.app.config.with_baselines_switch` puts that in the config)."""
    return {
        name: bcfg
        for name, bcfg in (cfg.get("baselines") or {}).items()
        if isinstance(bcfg, DictConfig) and "_target_" in bcfg
    }


def sweep_value(cfg: DictConfig, metrics: dict, run: RunResult | None = None):
    """The value(s) a sweep optimises (``optimized_metric``: one name, or a list for a multi-objective search;
    see :mod:`graf.search.objectives` for the names).  Only validation metrics and costs measured on
    validation data are accepted: nothing is chosen on the test split.  A NaN or missing metric is returned
    as NaN for the Optuna sweeper (which records the trial as failed) and as -inf for Hydra's basic sweeper."""
    names = cfg.get("optimized_metric")
    if not names:
        return 0.0
    single = isinstance(names, str)
    built = run.built if run is not None else None
    values = objective_values(
        [names] if single else list(names),
        metrics,
        scene_metrics=run.scene_metrics if run is not None else None,
        model=built.model if built else None,
        datamodule=built.evaluations[0].datamodule if built else None,
    )
    if not cfg.get("optuna_trial"):  # the worst value instead (a cost: +inf)
        worst = [float("inf") if str(n).startswith("cost/") else float("-inf") for n in ([names] if single else names)]
        for n, v in zip([names] if single else names, values):
            if not math.isfinite(v):
                log.warning("optimized metric %s is %s; reporting the worst value", n, v)
        values = [v if math.isfinite(v) else w for v, w in zip(values, worst)]
    return values[0] if single else values
