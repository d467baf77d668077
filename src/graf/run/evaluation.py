"""Testing a built run: validation and test of the final weights, neighbor reliance (the same figures with
each target's neighbors swapped for another target's), the baselines beside the model on the same data, and
what is written: ``results.json`` (+ ``predictions.npz``, ``spectra.png``, ``samples/``) and the printed table.

Every command writes ``results.json`` into its output folder::

    {"method", "scene", "band_hz", "n_train", "n_test",
     "metrics": {"val/mse", ..., "test/mse", "test/psnr", "test/ssim", "test/lpips", "test/reliance_db"},
     "seconds", "config", "splits", "ray_sampling", ...}

and, with ``save_predictions=true``, ``predictions.npz`` (``pred``, ``target``: float32 [N, 90, 360] in
[0, 1]; ``ids``: int [N]).  A figure of predicted vs true spectra (``spectra.png``) goes beside them.
"""

from __future__ import annotations

import logging
import math
import platform
import time
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

import graf
from graf.callbacks import PredictionCollector
from graf.io import atomic_write_json, atomic_write_npz, is_rank_zero
from graf.metrics.names import EVAL_METRICS
from graf.plotting import plot_spectra_grid
from graf.run.build import evaluation_trainer

log = logging.getLogger("graf")


def evaluate_model(cfg: DictConfig, model, dm, loggers=(), timing: dict | None = None) -> tuple[dict, dict]:
    """Validation then test metrics of ``model`` (``{val/..., test/...}``) and the test predictions; with
    ``timing`` (a dict), the wall seconds of each loop go into it (``val_s``, ``test_s``).  ``validate=false``
    (studies, which choose nothing) skips validation: the ``val/...`` figures are then None; ``test=false``
    (the trials of a hyperparameter search, which must not see the test split) skips the test: the
    ``test/...`` figures are then None."""
    collector = PredictionCollector()
    trainer = evaluation_trainer(cfg, loggers, [collector])
    t0 = time.perf_counter()
    metrics = {}
    if cfg.get("validate", True):
        trainer.validate(model=model, datamodule=dm, verbose=False)
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
    t1 = time.perf_counter()
    if cfg.get("test", True):
        trainer.test(model=model, datamodule=dm, verbose=False)
        metrics.update({k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")})
    t2 = time.perf_counter()
    if cfg.get("reliance", True) and getattr(model, "uses_neighbors", True):
        for split, done in (("val", cfg.get("validate", True)), ("test", cfg.get("test", True))):
            swapped = swapped_psnr(cfg, model, dm, split) if done else None
            if swapped is not None and metrics.get(f"{split}/psnr") is not None:
                metrics[f"{split}/psnr_swapped"] = swapped
                metrics[f"{split}/reliance_db"] = metrics[f"{split}/psnr"] - swapped
                for lg in trainer.loggers:  # beside the split's other figures (csv, wandb)
                    lg.log_metrics(
                        {f"{split}/psnr_swapped": swapped, f"{split}/reliance_db": metrics[f"{split}/reliance_db"]},
                        step=trainer.global_step,
                    )
                    lg.save()
    if timing is not None:
        timing.update(val_s=round(t1 - t0, 3), test_s=round(t2 - t1, 3), reliance_s=round(time.perf_counter() - t2, 3))
    return {k: metrics.get(k) for k in EVAL_METRICS}, collector.arrays()


def run_device(trainer, model) -> str:
    """The device the run trained and evaluated on, e.g. ``cuda:0 (NVIDIA H200)`` or ``cpu``.

    From the trainer's strategy, not the module: Lightning moves the module back to the CPU when a fit or test
    ends, so ``model.device`` read afterwards says ``cpu`` for a run that ran on a GPU."""
    dev = getattr(getattr(trainer, "strategy", None), "root_device", None)
    dev = torch.device(dev) if dev is not None else model.device
    if dev.type == "cuda" and torch.cuda.is_available():
        return f"{dev} ({torch.cuda.get_device_name(dev)})"
    return str(dev)


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


def test_and_report(cfg: DictConfig, objects: dict, started: float, task: str) -> dict:
    """Validate and test the model, then write results.json (+ predictions.npz, spectra.png).  Returns the
    metrics (``val/...`` and ``test/...``)."""
    trainer, model, train_dm = objects["trainer"], objects["model"], objects["datamodule"]
    evaluations = objects.get("evaluations") or [
        {"eval_scene": train_dm.scene_name, "datamodule": train_dm, "within_scene": True}
    ]
    timing = dict(objects.get("timing") or {})
    done = []
    for ev in evaluations:  # each test scene on its own (the first one's figures are the run's headline)
        t = dict(timing)
        m, a = evaluate_model(cfg, model, ev["datamodule"], objects["loggers"] if not done else (), t)
        done.append((ev, m, a, t))
    (first, metrics, arrays, timing) = done[0]
    # every test scene's figures, for objectives over all of them (val/psnr@mean; graf.search.objectives)
    objects["evaluation_metrics"] = [m for _, m, _, _ in done]
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
        "device": run_device(trainer, model),
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
    zero = is_rank_zero()  # the other ranks of a data-parallel run compute the same figures and write nothing
    if cfg.get("save_predictions") and zero:
        atomic_write_npz(out / "predictions.npz", **arrays)
        results["predictions"] = "predictions.npz"
    if int(cfg.get("plot_count", 0)) > 0 and len(arrays["ids"]) and zero:
        fig = plot_spectra_grid(
            arrays["pred"],
            arrays["target"],
            arrays["ids"],
            out / "spectra.png",
            title=f"{results['method']} on {dm.scene_name}",
            max_rows=int(cfg.plot_count),
        )
        results["figure"] = fig.name
        for lg in objects["loggers"]:
            if hasattr(lg, "log_image"):
                lg.log_image(key="test/spectra", images=[str(fig)])
    baselines = [(name, bcfg) for name, bcfg in selected_baselines(cfg).items() if bcfg != cfg.model]
    rows, per_eval = [], []
    for i, (ev, m, a, _t) in enumerate(done):  # every test scene: the model, then its baselines on the same data
        head = (
            results
            if i == 0
            else {"method": results["method"], "scene": ev["eval_scene"], "n_test": int(len(a["ids"])), "metrics": m}
        )
        brows = [_test_baseline(cfg, name, bcfg, ev["datamodule"]) for name, bcfg in baselines]
        if int(cfg.get("save_samples") or 0) > 0 and zero:
            for method, arr in [(results["method"], a)] + [(r["method"], r.pop("_arrays")) for r in brows]:
                save_samples(out, ev["eval_scene"], method, arr, int(cfg.save_samples))
        for r in brows:
            r.pop("_arrays", None)
        rows += [head, *brows]
        per_eval.append(
            {
                r["method"]: {
                    "metrics": r["metrics"],
                    "seconds": r["seconds"],
                    "trainable_parameters": r["trainable_parameters"],
                }
                for r in brows
            }
        )
    if per_eval[0]:
        results["baselines"] = per_eval[0]
    if len(done) > 1 or not first["within_scene"] or first["eval_scene"] != train_dm.scene_name:
        results["evaluations"] = [
            {
                "eval_scene": ev["eval_scene"],
                "within_scene": bool(ev["within_scene"]),
                "metrics": m,
                "n_test": int(len(a["ids"])),
                "band_hz": float(ev["datamodule"].bands[0].frequency_hz),
                "scene_index": int(ev["datamodule"].scene_index[0]),
                "splits": ev["datamodule"].split_summary(),
                "timing": t,
                "baselines": b,
            }
            for (ev, m, a, t), b in zip(done, per_eval)
        ]
    if objects.get("training"):  # steps asked and reached, and why training stopped early if it did
        results["training"] = objects["training"]
    if objects.get("resumed"):  # the checkpoint resumed from, and the trainer settings changed since
        results["resumed"] = objects["resumed"]
    if objects.get("finetune"):
        results["finetune"] = objects["finetune"]
    if objects.get("scene_table"):
        results["scene_table"] = objects["scene_table"]
    if cfg.get("regime"):
        results["regime"] = str(cfg.regime)
    if not zero:
        return metrics
    atomic_write_json(out / "results.json", results)
    print(format_metrics_table(rows))
    if "evaluations" in results:  # say which test scenes the model was trained on
        print(
            "; ".join(
                f"{e['eval_scene']}: {'within-scene (trained on it)' if e['within_scene'] else 'zero-shot'}"
                for e in results["evaluations"]
            )
        )
    if cfg.get("regime"):
        print(f"regime: {cfg.regime}")
    print(f"results: {out / 'results.json'}")
    if results.get("figure"):
        print(f"figure: {out / results['figure']}")
    return metrics


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
    """The baselines to test beside the model (``{name: model config}``).  ``baselines=null`` and ``baselines={}``
    both switch them off: Hydra merges ``{}`` into the composed group (a no-op), so the command line's own
    ``baselines={}`` is honoured here."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized() and any(
        o.replace(" ", "") in ("baselines={}", "baselines=null", "baselines=[]")
        for o in HydraConfig.get().overrides.task
    ):
        return {}
    return {
        name: bcfg
        for name, bcfg in (cfg.get("baselines") or {}).items()
        if isinstance(bcfg, DictConfig) and "_target_" in bcfg
    }


def _test_baseline(cfg: DictConfig, name: str, bcfg: DictConfig, dm) -> dict:
    """Validate and test a baseline (nothing trained) on the same datamodule, neighbors and splits."""
    started = time.perf_counter()
    model = hydra.utils.instantiate(bcfg)
    metrics, arrays = evaluate_model(cfg, model, dm)
    return {
        "method": getattr(model, "method", name),
        "scene": dm.scene_name,
        "n_test": int(len(arrays["ids"])),
        "trainable_parameters": int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
        "metrics": metrics,
        "seconds": round(time.perf_counter() - started, 3),
        "_arrays": arrays,
    }


def save_samples(out: Path, scene: str, method: str, arrays: dict, n: int) -> Path:
    """The first ``n`` test spectra of an evaluation (lowest ids: the same positions for every method on a
    scene) as ``samples/<scene>__<method>.npz`` (``pred``, ``target``: uint8 [n, 90, 360]; ``ids``), for
    graf-report's true-vs-predicted grids."""
    import numpy as np

    order = np.argsort(np.asarray(arrays["ids"]))[:n]
    q = lambda x: np.clip(np.rint(np.asarray(x)[order] * 255.0), 0, 255).astype(np.uint8)  # noqa: E731
    path = out / "samples" / f"{scene}__{method}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_npz(path, pred=q(arrays["pred"]), target=q(arrays["target"]), ids=np.asarray(arrays["ids"])[order])
    return path


def format_metrics_table(rows: list[dict]) -> str:
    """A plain-text table of the four test metrics (and the validation PSNR), one row per results dict."""
    head = (
        f"{'method':<22}{'scene':<16}{'n_test':>7}{'MSE':>10}{'PSNR':>9}{'SSIM':>8}{'LPIPS':>8}"
        f"{'val PSNR':>10}{'reliance dB':>13}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        m = r["metrics"]

        def f(key, spec, m=m):
            v = m.get(key)
            width = spec.split(".")[0]
            return format(v, spec) if v is not None and not math.isnan(v) else format("n/a", f">{width}")

        lines.append(
            f"{r['method']:<22}{r['scene']:<16}{r['n_test']:>7}{f('test/mse', '10.4f')}"
            f"{f('test/psnr', '9.2f')}{f('test/ssim', '8.3f')}{f('test/lpips', '8.3f')}"
            f"{f('val/psnr', '10.2f')}{f('test/reliance_db', '13.2f')}"
        )
    return "\n".join(lines)


def sweep_value(cfg: DictConfig, metrics: dict, objects: dict | None = None):
    """The value(s) a sweep optimises (``optimized_metric``: one name, or a list for a multi-objective search;
    see :mod:`graf.search.objectives` for the names).  Only validation metrics and costs measured on
    validation data are accepted: nothing is chosen on the test split.  A NaN or missing metric is returned
    as NaN for the Optuna sweeper (which records the trial as failed) and as -inf for Hydra's basic sweeper."""
    from graf.search.objectives import objective_values

    names = cfg.get("optimized_metric")
    if not names:
        return 0.0
    single = isinstance(names, str)
    values = objective_values([names] if single else list(names), metrics, objects or {})
    if not cfg.get("optuna_trial"):  # the worst value instead (a cost: +inf)
        worst = [float("inf") if str(n).startswith("cost/") else float("-inf") for n in ([names] if single else names)]
        for n, v in zip([names] if single else names, values):
            if not math.isfinite(v):
                log.warning("optimized metric %s is %s; reporting the worst value", n, v)
        values = [v if math.isfinite(v) else w for v, w in zip(values, worst)]
    return values[0] if single else values
