"""What graf-train and graf-eval share: building the run from the config, validating and testing the
final weights, and writing results.

Every command writes ``results.json`` into its Hydra output folder::

    {"method", "scene", "band_hz", "n_train", "n_test",
     "metrics": {"val/mse", ..., "test/mse", "test/psnr", "test/ssim", "test/lpips"}, "seconds", "config",
     "splits", "ray_sampling", ...}

and, with ``save_predictions=true``, ``predictions.npz`` (``pred``, ``target``: float32 [N, 90, 360] in
[0, 1]; ``ids``: int [N]).  A figure of predicted vs true spectra (``spectra.png``) goes beside them.
"""

from __future__ import annotations

import functools
import logging
import math
import platform
import time
from pathlib import Path

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

import graf
from graf.callbacks import PredictionCollector
from graf.io import atomic_write_json, atomic_write_npz
from graf.plotting import plot_spectra_grid

log = logging.getLogger("graf")

# The configs ship inside the package (src/graf/conf; conf/ in the checkout links to it).  Every
# @hydra.main reads them as a package resource, so an installed wheel works from any folder; add a
# folder of your own with Hydra's --config-dir.  CONF_DIR is the same folder on disk (for tests).
CONF_PATH = "pkg://graf.conf"
CONF_DIR = Path(graf.__file__).resolve().parent / "conf"


def task_wrapper(task):
    """Run a task; on failure log the exception (and the output folder) before re-raising; always close
    the loggers (wandb included), so a failed run in a sweep leaves a finished, inspectable record."""

    @functools.wraps(task)
    def wrapped(cfg: DictConfig, *args, **kwargs):
        try:
            return task(cfg, *args, **kwargs)
        except Exception:
            log.exception("%s failed; output folder: %s", cfg.get("task_name", "task"), _output_dir(cfg))
            raise
        finally:
            try:
                import wandb

                if wandb.run is not None:
                    wandb.finish()
            except ImportError:  # pragma: no cover
                pass

    return wrapped


def _output_dir(cfg: DictConfig) -> Path:
    try:
        return Path(cfg.paths.output_dir)
    except Exception:  # ${hydra:...} outside a Hydra app
        return Path.cwd()


class ConfigError(ValueError):
    """A configuration that cannot run as given; the message says what to set."""


METRIC_NAMES = ("mse", "psnr", "ssim", "lpips")
EVAL_METRICS = tuple(f"{s}/{m}" for s in ("val", "test") for m in METRIC_NAMES)


def scene_configs(node) -> list[DictConfig]:
    """The scene configs a ``scene`` or ``eval_scene`` node selects, in order.  ``scene=conference_v1`` composes
    to ``scene.conference_v1: {...}`` and ``scene=[conference_v1,office_v1]`` to one entry per scene (Hydra's
    list selection; each option places ``scene_catalog/<name>`` under its own name); a flat config with a
    ``_target_`` (graf-bench's ``scenes.<key>``) is one scene."""
    if node is None:
        return []
    if isinstance(node, DictConfig) and "_target_" in node:
        return [node]
    return [v for v in node.values() if isinstance(v, DictConfig) and "_target_" in v]


def single_scene_config(cfg: DictConfig, command: str) -> DictConfig:
    """The one scene of a command that works on one scene (graf-simulate, graf-oracle, graf-synthesize)."""
    scenes = scene_configs(cfg.get("scene"))
    if len(scenes) != 1:
        raise ConfigError(f"{command} works on one scene; scene= selects {len(scenes)} "
                          f"({', '.join(str(s.get('name')) for s in scenes) or 'none'})")
    return scenes[0]


def band_choices() -> list[str]:
    """The options of the ``band`` config group."""
    return sorted(p.stem for p in (CONF_DIR / "band").glob("*.yaml"))


def load_band_config(name: str) -> DictConfig:
    path = CONF_DIR / "band" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"unknown band {name!r}: one of {', '.join(band_choices())}")
    return OmegaConf.load(path)


def scene_band_config(scene_cfg: DictConfig, run_band: DictConfig | None) -> DictConfig:
    """A scene's band: its own when fixed (measured data: rfid_s23 is 915 MHz whatever the run says), else the
    run's ``band=...``, else the scene's default (simulated scenes: 2.4 GHz, the paper's band)."""
    own = scene_cfg.get("band")
    if scene_cfg.get("fixed_band") and own:
        return load_band_config(own)
    if run_band is not None:
        return run_band
    if own:
        return load_band_config(own)
    raise ConfigError(f"scene {scene_cfg.get('name', '?')!r} does not say its carrier frequency: add "
                      f"band=<one of {', '.join(band_choices())}> (the band its spectra were measured at)")


def build_datamodule(cfg: DictConfig, which: str = "scene", scene_indices=None):
    """Bands, scenes, neighbour selector and the datamodule that joins them (``cfg.data``), for the scenes
    of ``cfg[which]`` (``scene``: what is trained on; ``eval_scene``: what is tested)."""
    configs = scene_configs(cfg.get(which))
    if not configs:
        raise ConfigError(f"{which}= selects no scene")
    band_cfgs = [scene_band_config(c, cfg.get("band")) for c in configs]
    bands = [hydra.utils.instantiate(b) for b in band_cfgs]
    scenes = [hydra.utils.instantiate(c) for c in configs]
    neighbors = hydra.utils.instantiate(cfg.neighbors)
    make = hydra.utils.instantiate(cfg.data, _partial_=True)  # lists of objects must not pass through OmegaConf
    datamodule = make(scene=scenes, band=bands, neighbors=neighbors, data_root=cfg.get("data_root"),
                      scene_indices=scene_indices)
    return bands, scenes, neighbors, datamodule


def eval_scene_indices(train_names: list[str], eval_names: list[str]) -> list[int]:
    """The scene index of each test scene: its training index when the model was trained on it, else a new
    index after the training scenes' (an unseen scene)."""
    out, new = [], len(train_names)
    for n in eval_names:
        if n in train_names:
            out.append(train_names.index(n))
        else:
            out.append(new)
            new += 1
    return out


def build(cfg: DictConfig) -> dict:
    """Instantiate band, scene, neighbour selector, datamodule (set up), model, loggers and trainer."""
    if cfg.get("seed") is not None:
        L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out = _output_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    _, _, neighbors, datamodule = build_datamodule(cfg)
    datamodule.setup("fit")
    evaluations = eval_datamodules(cfg, datamodule)
    model = hydra.utils.instantiate(cfg.model)
    loggers = [hydra.utils.instantiate(c) for c in (cfg.get("logger") or {}).values()
               if isinstance(c, DictConfig) and "_target_" in c]
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values()
                 if isinstance(c, DictConfig) and "_target_" in c]
    trainer = hydra.utils.instantiate(trainer_args(cfg), logger=loggers or False, callbacks=callbacks)
    return {"neighbors": neighbors, "datamodule": datamodule, "evaluations": evaluations, "model": model,
            "loggers": loggers, "trainer": trainer, "output_dir": out}


def eval_datamodules(cfg: DictConfig, train_dm) -> list[dict]:
    """What the final evaluations test: ``[{"eval_scene", "datamodule", "within_scene"}]``.  Without
    ``eval_scene`` (``eval_scene=same``) the training datamodule itself (within-scene).  Otherwise one
    datamodule per test scene, its targets from that scene's splits and their neighbours from that scene's
    training split; a test scene the model was trained on keeps its training scene index and is reported
    as within-scene, an unseen one gets a new index."""
    configs = scene_configs(cfg.get("eval_scene"))
    if not configs:
        return [{"eval_scene": train_dm.scene_name, "datamodule": train_dm, "within_scene": True}]
    train_names = [d.name for d in train_dm.sets]
    names = [str(c.get("name")) for c in configs]
    indices = eval_scene_indices(train_names, names)
    out = []
    for c, name, k in zip(configs, names, indices):
        sub = OmegaConf.create({key: OmegaConf.to_container(v, resolve=True) if isinstance(v, DictConfig) else v
                                for key, v in (("eval_scene", OmegaConf.create({name: c})), ("band", cfg.get("band")),
                                             ("neighbors", cfg.neighbors), ("data", cfg.data),
                                             ("data_root", cfg.get("data_root")))})
        _, _, _, dm = build_datamodule(sub, "eval_scene", scene_indices=[k])
        dm.setup("test")
        within = name in train_names
        log.info("test scene %s: %s (scene index %d)", name, "within-scene (also trained on)" if within
                 else "unseen in training (zero-shot)", k)
        out.append({"eval_scene": name, "datamodule": dm, "within_scene": within})
    return out


def ray_sampling(model, dm) -> dict | None:
    """Samples per ray and the effective voxel (sample spacing) of a ray-rendering model on each of the
    datamodule's scenes; logs a warning where ``max_samples`` caps S (voxels longer than nominal)."""
    out = {}
    for k, d in enumerate(dm.sets):
        geometry = {"ray_length": dm.ray_length[k:k + 1], "wavelength": dm.wavelength[k:k + 1],
                    "gw_pos": dm.gw_pos[k:k + 1], "gw_rot": dm.gw_rot[k:k + 1], "bounds": dm.bounds[k:k + 1],
                    "scene_index": dm.scene_index[k:k + 1]}
        r = model.ray_sampling(geometry)
        if r is None:
            return None
        out[d.name] = r
        if r["capped"]:
            log.warning("%s on %s: max_samples caps the samples per ray at %d (%d needed), so each sample spans "
                        "%.2f wavelengths (%.3f m) instead of %.2f", type(model).__name__, d.name,
                        r["samples_per_ray"], r["uncapped_samples"], r["sample_spacing_wavelengths"],
                        r["sample_spacing_m"], r["nominal_spacing_wavelengths"])
    return out


def trainer_args(cfg: DictConfig) -> DictConfig:
    """``cfg.trainer`` without the keys that are not Trainer arguments, after applying them:
    ``float32_matmul_precision`` (``highest`` | ``high`` = TF32 on NVIDIA GPUs | ``medium``; null: torch's)."""
    t = OmegaConf.to_container(cfg.trainer, resolve=True)
    fmp = t.pop("float32_matmul_precision", None)
    if fmp:
        torch.set_float32_matmul_precision(str(fmp))
    return OmegaConf.create(t)


def evaluation_trainer(cfg: DictConfig, loggers=(), callbacks=()) -> L.Trainer:
    """The trainer of the final evaluations (validation and test of the final weights).  Both evaluate
    ``trainer.limit_test_batches`` of their split; validation during training (off by default) is the fit
    trainer's business."""
    t = trainer_args(cfg)
    limit = t.get("limit_test_batches", 1.0)
    return L.Trainer(accelerator=t.get("accelerator", "auto"), devices=t.get("devices", 1),
                     precision=t.get("precision", "32-true"), logger=list(loggers) or False,
                     callbacks=list(callbacks), enable_progress_bar=bool(t.get("enable_progress_bar", True)),
                     enable_model_summary=False, enable_checkpointing=False, limit_val_batches=limit,
                     limit_test_batches=limit, default_root_dir=t.get("default_root_dir"))


def evaluate_model(cfg: DictConfig, model, dm, loggers=(), timing: dict | None = None) -> tuple[dict, dict]:
    """Validation then test metrics of ``model`` (``{val/..., test/...}``) and the test predictions; with
    ``timing`` (a dict), the wall seconds of each loop go into it (``val_s``, ``test_s``)."""
    collector = PredictionCollector()
    trainer = evaluation_trainer(cfg, loggers, [collector])
    t0 = time.perf_counter()
    trainer.validate(model=model, datamodule=dm, verbose=False)
    t1 = time.perf_counter()
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
    trainer.test(model=model, datamodule=dm, verbose=False)
    t2 = time.perf_counter()
    metrics.update({k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")})
    if timing is not None:
        timing.update(val_s=round(t1 - t0, 3), test_s=round(t2 - t1, 3))
    return {k: metrics.get(k) for k in EVAL_METRICS}, collector.arrays()


def test_and_report(cfg: DictConfig, objects: dict, started: float, task: str) -> dict:
    """Validate and test the model, then write results.json (+ predictions.npz, spectra.png).  Returns the
    metrics (``val/...`` and ``test/...``)."""
    trainer, model, train_dm = objects["trainer"], objects["model"], objects["datamodule"]
    evaluations = objects.get("evaluations") or [{"eval_scene": train_dm.scene_name, "datamodule": train_dm,
                                                   "within_scene": True}]
    timing = dict(objects.get("timing") or {})
    done = []
    for ev in evaluations:  # each test scene on its own (the first one's figures are the run's headline)
        t = dict(timing)
        m, a = evaluate_model(cfg, model, ev["datamodule"], objects["loggers"] if not done else (), t)
        done.append((ev, m, a, t))
    (first, metrics, arrays, timing) = done[0]
    dm = first["datamodule"]
    out: Path = objects["output_dir"]
    config = OmegaConf.to_container(cfg, resolve=True)
    if objects.get("checkpoint"):  # graf-eval of a checkpoint: the model that ran is the checkpoint's
        config["model"] = objects["checkpoint"]["model"]
    results = {
        "method": getattr(model, "method", type(model).__name__),
        "scene": dm.scene_name,
        "train_scenes": [d.name for d in train_dm.sets],
        "eval_scene": first["eval_scene"],
        "within_scene": bool(first["within_scene"]),
        "band_hz": float(dm.bands[0].frequency_hz),
        "train_bands_hz": [float(b.frequency_hz) for b in train_dm.bands],
        "n_train": dm.n_train,
        "n_test": int(len(arrays["ids"])),
        "metrics": metrics,
        "seconds": round(time.perf_counter() - started, 3),
        "config": config,
        "task": task,
        "eval_split": dm.eval_split,
        "split_source": "; ".join(d.split_source for d in dm.sets),
        "splits": dm.split_summary(),
        "neighbors": repr(objects["neighbors"]),
        "trainable_parameters": int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
        "global_step": int(objects.get("checkpoint", {}).get("global_step", trainer.global_step)),
        "device": str(model.device),
        "versions": {"graf": graf.__version__, "torch": torch.__version__, "python": platform.python_version()},
    }
    n_test = int(len(arrays["ids"]))
    if n_test:  # the whole test loop (prediction and the four metrics) per spectrum
        timing["test_s_per_spectrum"] = round(timing["test_s"] / n_test, 4)
    results["timing"] = timing
    sampling = ray_sampling(model, dm)
    if sampling is not None:
        results["ray_sampling"] = sampling
    if objects.get("checkpoint"):
        results["checkpoint"] = {k: v for k, v in objects["checkpoint"].items() if k != "model"}
    if cfg.get("save_predictions"):
        atomic_write_npz(out / "predictions.npz", **arrays)
        results["predictions"] = "predictions.npz"
    if int(cfg.get("plot_count", 0)) > 0 and len(arrays["ids"]):
        fig = plot_spectra_grid(arrays["pred"], arrays["target"], arrays["ids"], out / "spectra.png",
                                title=f"{results['method']} on {dm.scene_name}", max_rows=int(cfg.plot_count))
        results["figure"] = fig.name
        for lg in objects["loggers"]:
            if hasattr(lg, "log_image"):
                lg.log_image(key="test/spectra", images=[str(fig)])
    baselines = [(name, bcfg) for name, bcfg in (cfg.get("baselines") or {}).items()
                 if isinstance(bcfg, DictConfig) and "_target_" in bcfg and bcfg != cfg.model]
    rows, per_eval = [], []
    for i, (ev, m, a, t) in enumerate(done):  # every test scene: the model, then its baselines on the same data
        head = results if i == 0 else {"method": results["method"], "scene": ev["eval_scene"],
                                       "n_test": int(len(a["ids"])), "metrics": m}
        brows = [_test_baseline(cfg, name, bcfg, ev["datamodule"]) for name, bcfg in baselines]
        rows += [head, *brows]
        per_eval.append({r["method"]: {"metrics": r["metrics"], "seconds": r["seconds"],
                                       "trainable_parameters": r["trainable_parameters"]} for r in brows})
    if per_eval[0]:
        results["baselines"] = per_eval[0]
    if len(done) > 1 or not first["within_scene"] or first["eval_scene"] != train_dm.scene_name:
        results["evaluations"] = [
            {"eval_scene": ev["eval_scene"], "within_scene": bool(ev["within_scene"]), "metrics": m,
             "n_test": int(len(a["ids"])), "band_hz": float(ev["datamodule"].bands[0].frequency_hz),
             "scene_index": int(ev["datamodule"].scene_index[0]), "splits": ev["datamodule"].split_summary(),
             "timing": t, "baselines": b} for (ev, m, a, t), b in zip(done, per_eval)]
    if cfg.get("regime"):
        results["regime"] = str(cfg.regime)
    atomic_write_json(out / "results.json", results)
    log.info("results: %s", out / "results.json")
    print(format_metrics_table(rows))
    if cfg.get("regime"):
        print(f"regime: {cfg.regime}")
    return metrics


def _test_baseline(cfg: DictConfig, name: str, bcfg: DictConfig, dm) -> dict:
    """Validate and test a baseline (nothing trained) on the same datamodule, neighbours and splits."""
    started = time.perf_counter()
    model = hydra.utils.instantiate(bcfg)
    metrics, arrays = evaluate_model(cfg, model, dm)
    return {"method": getattr(model, "method", name), "scene": dm.scene_name, "n_test": int(len(arrays["ids"])),
            "trainable_parameters": int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
            "metrics": metrics, "seconds": round(time.perf_counter() - started, 3)}


def format_metrics_table(rows: list[dict]) -> str:
    """A plain-text table of the four test metrics (and the validation PSNR), one row per results dict."""
    head = (f"{'method':<22}{'scene':<16}{'n_test':>7}{'MSE':>10}{'PSNR':>9}{'SSIM':>8}{'LPIPS':>8}"
            f"{'val PSNR':>10}")
    lines = [head, "-" * len(head)]
    for r in rows:
        m = r["metrics"]

        def f(key, spec):
            v = m.get(key)
            return format(v, spec) if v is not None and not math.isnan(v) else "n/a"

        lines.append(f"{r['method']:<22}{r['scene']:<16}{r['n_test']:>7}{f('test/mse', '10.4f')}"
                     f"{f('test/psnr', '9.2f')}{f('test/ssim', '8.3f')}{f('test/lpips', '8.3f')}"
                     f"{f('val/psnr', '10.2f')}")
    return "\n".join(lines)


def sweep_value(cfg: DictConfig, metrics: dict) -> float:
    """The value a sweep optimises: never NaN (a NaN or missing metric counts as the worst value)."""
    name = cfg.get("optimized_metric")
    if not name:
        return 0.0
    if not str(name).startswith("val/"):
        raise ConfigError(f"optimized_metric={name}: a sweep may optimise a validation metric (val/...) only; "
                          "nothing is chosen on the test split")
    v = metrics.get(name)
    if v is None or not math.isfinite(v):
        log.warning("optimized metric %s is %s; reporting -inf", name, v)
        return float("-inf")
    return float(v)
