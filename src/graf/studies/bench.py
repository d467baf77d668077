"""graf-bench: the methods' cost side by side on a real and a simulated scene.

    graf-bench [quick=true] [threads=N] [bench.models=[knn,graf_cpu]] [bench.scenes=[real]] [data_root=DIR]

For every scene of ``scenes`` (default: ``real`` = the embedded rfid_s23 at 915 MHz, ``room`` = the
simulated conference_v1 at 2.4 GHz) and every model of ``models`` (default: ``graf``, ``graf_cpu``,
``graf_cpu_ray_weights``, ``nerf2``, ``nerf2_cpu``, ``rf_gs``, ``knn_dl``, ``knn``: the model configs of those
names) it measures, one row each:

- ``infer_s_per_spectrum``: the median over the first ``bench.spectra`` test spectra of the time of one
  ``predict_spectra`` call on a batch of one spectrum (``time.perf_counter``; ``torch.cuda.synchronize()``
  before and after each on CUDA), after one warm-up spectrum, in eval mode without autograd.  Caches a
  model keeps between spectra (GRaF's encoder features of neighbors it has seen) are used as at test time.
- ``train_s_per_step``: the median over ``bench.train_steps`` optimiser steps, after one warm-up step, of
  ``loss = model.training_step(batch, i); loss.backward(); opt.step(); opt.zero_grad()`` (and the
  scheduler's step, as Lightning does every step), on the datamodule's own training batches
  (``train_batch(k)``, ``data.batch_size`` targets each, built before the clock starts).  The optimiser and
  scheduler are the model's ``configure_optimizers()``.  No Trainer runs: ``training_step``'s
  ``self.log`` is replaced by a no-op (without a Trainer Lightning's own ``log`` does nothing but warn) and
  ``global_step`` stays 0.  Models with a ``rays_per_step`` setting (GRaF, NeRF2) are built with
  ``bench.rays_per_step`` (5,120: the paper's), split evenly across the batch's targets
  (``train_rays_per_step`` records the rays actually rendered); a model without one (KNN-DL, RF-GS) trains on
  whole spectra, 32,400 rays per target.  ``train_rays_per_s`` = rays per step / seconds per step.
  Models without trainable parameters (KNN): null.
- ``peak_mb_infer`` / ``peak_mb_train`` (``peak_mb``: the larger): the phase's peak memory above its
  start, in MiB.  On CPU the process's resident set size (``/proc/self/statm``), sampled every 5 ms by a
  thread during the phase (after ``gc.collect()`` and glibc's ``malloc_trim``, so memory freed by earlier
  rows is given back first), peak minus the value at the phase's start; the model's weights, already
  resident, are not counted, but the optimiser's state, gradients and activations are.  On CUDA
  ``torch.cuda.max_memory_allocated()`` after ``torch.cuda.reset_peak_memory_stats()``, minus the memory
  allocated at the phase's start.  ``results.json`` says which (``memory``).
- ``parameters`` (all) and ``trainable_parameters``; ``checkpoint_mb``: the size of a weights-only
  Lightning checkpoint of the model, in MiB.
- ``samples_per_ray``: for ray-rendering models, the mean voxels per ray where the model reports it
  (``mean_samples_per_ray``: GRaF, whose rays end at the scene box), else ``samples_per_ray(batch)[0]``
  (NeRF2); null for KNN and KNN-DL.
- ``infer_ratio_to_graf`` / ``train_ratio_to_graf``: the row's ``infer_s_per_spectrum`` (``train_s_per_step``)
  over that of the scene's *ratio base*: the row of preset ``graf`` (the paper's sizes) on the same scene,
  or, where that is absent or failed, the scene's first row whose method is GRaF (``graf``/``graf-residual``);
  null where there is none.  ``ratio_base`` in results.json names it per scene.
- ``infer_load_cores`` / ``train_load_cores``: the cores other processes used while the phase was timed
  (``/proc``: :mod:`graf.studies.bench_load`); ``infer_spread`` / ``train_spread``: ``(max - min) / median`` of
  the repeated timings (null for one); ``disturbed`` and ``disturbances``: the row's timings are not a quiet
  measurement (load above 0.2 cores or spread above 15%: ``disturbance_limits``).
- ``bench.compete=true``: after the quiet timing, the model's evaluation caches are emptied and the warm-up and
  the timed spectra run again beside a competing single-threaded process the bench starts
  (``infer_s_per_spectrum_loaded``, ``infer_load_cores_loaded``) and ``infer_slowdown`` = loaded / quiet: the
  methods side by side under the same load; likewise the timed training steps (``train_s_per_step_loaded``,
  ``train_load_cores_loaded``, ``train_slowdown``).

Everything runs on the GPU when ``torch.cuda.is_available()`` (``device_type``: ``cuda``; the table's first
line names the device), else on the CPU with ``threads`` threads (null: torch's default; recorded).
``precision=bf16``: every row's measurements under ``torch.autocast`` to bfloat16 (``32``, the default: none;
recorded as ``precision``).

Simulated scenes read their limited dataset ``<data_root>/sim/<scene>/<band>-n<N>.h5`` (N =
``bench.sim_num_tx`` unless the scene sets ``num_tx``); when the file is missing it is made first, by the
code of ``graf-simulate scene=<scene> band=<band> sim.num_tx=N`` (its results.json goes to
``simulate/<key>/`` in the output folder).

Writes into the Hydra output folder ``results.json`` (``rows``: one entry per (scene, model); ``device``,
``threads``, ``torch``, ``spectra_timed``, ``train_steps_timed``, ``memory``, ``ratio_base``, ``config``)
and ``bench.md`` (the printed table), both rewritten atomically after every row, so a killed run keeps what
it measured.  A row that fails (a model that cannot run, a scene whose data cannot be read or simulated)
is logged and recorded with an ``error`` field, and the others still run.

``quick=true`` (a check that every configuration runs, in minutes on a 2-core CPU): one timed spectrum and
one timed training step instead of ``bench.spectra`` and ``bench.train_steps``, each after a *light*
warm-up: for inference one chunk of the model's ``chunk_rays`` rays through its ``prepare`` and ``render``
(GRaF, NeRF2; the others warm up on a whole spectrum), for training one optimiser step at 256 rays (models
with ``rays_per_step``).  The timed spectrum and step are whole, as without ``quick``; every configuration
still runs.  ``warmup`` in results.json says which warm-up ran.
"""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from graf.app.config import (
    CONF_DIR,
    band_choices,
    check_bool,
    check_int,
    check_run_settings,
    output_dir,
    task_wrapper,
)
from graf.app.spec import RunSpec
from graf.errors import ConfigError
from graf.run.build import build_datamodule, model_config_for_neighbors
from graf.sim.simulate import simulate
from graf.studies.bench_load import LOAD_LIMIT, SPREAD_LIMIT, disturbances
from graf.studies.bench_measure import (
    checkpoint_mb,
    device_name,
    measure_inference,
    measure_training,
    memory_method,
    release_memory,
    samples_per_ray,
    to_device,
)
from graf.studies.bench_report import fmt, markdown, write_result

log = logging.getLogger("graf")
PRECISIONS = ("32", "bf16")

ROW_KEYS = (
    "method",
    "preset",
    "scene",
    "samples_per_ray",
    "infer_s_per_spectrum",
    "train_s_per_step",
    "train_rays_per_s",
    "peak_mb_train",
    "peak_mb_infer",
    "peak_mb",
    "parameters",
    "checkpoint_mb",
    "infer_ratio_to_graf",
    "train_ratio_to_graf",
    "infer_load_cores",
    "train_load_cores",
    "infer_spread",
    "train_spread",
    "disturbed",
)
WARMUP = {
    "whole": "one whole spectrum before the timed ones; one whole training step before the timed ones",
    "light": "quick: one chunk of chunk_rays rays (GRaF, NeRF2; a whole spectrum for the others) before the "
    "timed spectrum; one training step at 256 rays (models with rays_per_step) before the timed one",
}


# ---------------------------------------------------------------------------------------------- scenes
def scene_and_band(cfg: DictConfig, key: str) -> tuple[DictConfig, DictConfig]:
    """The scene config ``scenes.<key>`` (with ``num_tx = bench.sim_num_tx`` for a simulated scene that
    sets none) and its band ``bands.<key>``."""
    bands = cfg.get("bands") or {}
    if key not in bands:
        raise ConfigError(f"scene {key!r} has no band: add +band@bands.{key}=<one of {', '.join(band_choices())}>")
    scene_cfg = OmegaConf.create(OmegaConf.to_container(cfg.scenes[key], resolve=True))
    n = cfg.bench.get("sim_num_tx")
    if "num_tx" in scene_cfg and scene_cfg.num_tx is None and n is not None:
        scene_cfg.num_tx = int(n)
    return scene_cfg, bands[key]


def ensure_simulated(cfg: DictConfig, key: str, scene_cfg: DictConfig, band_cfg: DictConfig) -> Path | None:
    """For a simulated scene: its dataset file; made first (graf-simulate's code, ``sim.num_tx`` = the
    scene's ``num_tx``) when it is not under ``data_root``.  None for other scenes (nothing to make)."""
    scene = hydra.utils.instantiate(scene_cfg)
    if not hasattr(scene, "dataset_path"):
        return None
    band = hydra.utils.instantiate(band_cfg)
    path = scene.dataset_path(cfg.data_root, band, scene.num_tx)
    if path.is_file():
        return path
    log.info(
        "%s is not there: simulating %s positions of %s at %s first", path, scene.num_tx or "all", scene.name, band.name
    )
    try:
        sim = OmegaConf.load(CONF_DIR / "simulate.yaml").sim
    except Exception:  # pragma: no cover - the config ships with the package
        sim = OmegaConf.create({"chunk_size": 256, "export": None, "overwrite": False, "device": "auto"})
    sim = OmegaConf.merge(sim, {"num_tx": scene.num_tx, "progress": False})
    scfg = OmegaConf.create(
        {
            "task_name": "simulate",
            "data_root": cfg.data_root,
            "scene": scene_cfg,
            "band": band_cfg,
            "sim": sim,
            "paths": {"output_dir": str(output_dir(cfg) / "simulate" / key)},
        }
    )
    simulate(scfg)
    return path


def prepare_scene(cfg: DictConfig, key: str, spectra: int, train_steps: int):
    """``(datamodule, inference batches [1 + spectra], training batches [1 + train_steps], band name)``."""
    scene_cfg, band_cfg = scene_and_band(cfg, key)
    ensure_simulated(cfg, key, scene_cfg, band_cfg)
    dcfg = OmegaConf.create(
        {
            "scene": scene_cfg,
            "band": band_cfg,
            "data_root": cfg.get("data_root"),
            "neighbors": OmegaConf.to_container(cfg.neighbors, resolve=True),
            "data": OmegaConf.to_container(cfg.data, resolve=True),
        }
    )
    bands, _, _, dm = build_datamodule(RunSpec.of(dcfg))
    band = bands[0]
    dm.setup("fit")
    infer = [dm.eval_batch([i]) for i in range(min(spectra + 1, len(dm.eval_rows)))]
    train = [dm.train_batch(k) for k in range(train_steps + 1)]
    return dm, infer, train, band.name


def autocast(cfg: DictConfig, device: torch.device):
    """``precision=bf16``: torch.autocast to bfloat16 on ``device`` around a row's measurements; ``32``: nothing."""
    precision = str(cfg.get("precision", 32))
    if precision not in PRECISIONS:
        raise ConfigError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    return torch.autocast(device.type, dtype=torch.bfloat16) if precision == "bf16" else contextlib.nullcontext()


def _selected(cfg: DictConfig, group: str, only_key: str) -> list[str]:
    keys = [k for k, v in (cfg.get(group) or {}).items() if isinstance(v, DictConfig) and "_target_" in v]
    only = cfg.bench.get(only_key)
    if only is None:
        return keys
    unknown = [k for k in only if k not in keys]
    if unknown:
        raise ConfigError(f"bench.{only_key}: {unknown} not among the {group} of this run ({', '.join(keys)})")
    return [k for k in keys if k in set(only)]


# ---------------------------------------------------------------------------------------------- the command
@task_wrapper
def bench(cfg: DictConfig) -> dict:
    """graf-bench: one row per (scene, model) of ``cfg`` (module doc), written after each; the result."""
    check_run_settings(cfg)  # a seed numpy refuses, before anything runs
    if check_int(cfg.get("threads"), "threads", none=True) is not None:  # torch refused 0 with a traceback
        torch.set_num_threads(cfg.threads)
    quick = check_bool(cfg.get("quick", False), "quick")
    check_bool(cfg.bench.get("compete", False), "bench.compete")  # a string such as "no" ran as true
    spectra = 1 if quick else check_int(cfg.bench.spectra, "bench.spectra")
    steps = 1 if quick else check_int(cfg.bench.train_steps, "bench.train_steps")
    autocast(cfg, torch.device("cpu"))  # an unknown precision is refused before anything runs
    scene_keys, model_keys = _selected(cfg, "scenes", "scenes"), _selected(cfg, "models", "models")
    for key in scene_keys:
        scene_and_band(cfg, key)  # every scene has its band before anything runs
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    out = output_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    result = {
        "device": device_name(device),
        "device_type": device.type,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "quick": quick,
        "spectra_timed": spectra,
        "train_steps_timed": steps,
        "warmup": WARMUP["light" if quick else "whole"],
        "rays_per_step": cfg.bench.get("rays_per_step"),
        "compete": bool(cfg.bench.get("compete")),
        "precision": str(cfg.get("precision", 32)),
        "disturbance_limits": {"load_cores": LOAD_LIMIT, "spread": SPREAD_LIMIT},
        "memory": memory_method(device),
        "ratio_base": {},
        "rows": [],
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    skip = set(cfg.bench.get("quick_skip") or []) if quick else set()
    result["skipped"] = [f"{k}/{m}" for k in scene_keys for m in model_keys if f"{k}/{m}" in skip]
    for key in scene_keys:
        _bench_scene(cfg, key, model_keys, skip, device, out, result)
    write_result(out, result)
    print(markdown(result))
    log.info("results: %s", out / "results.json")
    return result


def _bench_scene(
    cfg: DictConfig, key: str, model_keys: list[str], skip: set, device: torch.device, out: Path, result: dict
) -> None:
    """The rows of scene ``key``: one per model of ``model_keys`` not in ``skip`` (``<scene>/<model>``), or, when
    its data cannot be prepared, one error row per model."""
    started = time.perf_counter()
    try:
        dm, infer, train, band_name = prepare_scene(cfg, key, result["spectra_timed"], result["train_steps_timed"])
        scene_name = dm.data.name
        infer = [to_device(b, device) for b in infer]
        train = [to_device(b, device) for b in train]
    except Exception as exc:
        log.exception("scene %s: could not prepare its data; its rows record the error", key)
        name = cfg.scenes[key].get("name", key)
        error = {"error": f"{type(exc).__name__}: {exc}", "seconds": round(time.perf_counter() - started, 3)}
        for m in model_keys:
            result["rows"].append({**dict.fromkeys(ROW_KEYS), "scene": name, "scene_key": key, "preset": m, **error})
        write_result(out, result)
        return
    log.info(
        "scene %s (%s): %d test spectra, %d training batches of %d targets prepared",
        scene_name,
        band_name,
        len(infer),
        len(train),
        int(train[0]["tgt_pos"].shape[0]),
    )
    for m in model_keys:
        if f"{key}/{m}" in skip:
            log.info("%s on %s: skipped (quick=true, bench.quick_skip)", m, scene_name)
            continue
        started = time.perf_counter()
        row = {"scene": scene_name, "scene_key": key, "band": band_name, "preset": m, "method": None}
        row.update(_bench_model(cfg, m, scene_name, infer, train, device))
        row["seconds"] = round(time.perf_counter() - started, 3)
        result["rows"].append({**dict.fromkeys(ROW_KEYS), **row})
        write_result(out, result)
        error = row.get("error")
        times = f"{fmt(row.get('infer_s_per_spectrum'))} s/spectrum, {fmt(row.get('train_s_per_step'))} s/step"
        log.info("%s on %s: %s", m, scene_name, "error" if error else times)


def _bench_model(cfg: DictConfig, m: str, scene_name: str, infer: list, train: list, device: torch.device) -> dict:
    """The measurements of model preset ``m`` on a scene's batches; ``{"error": ...}`` (and what was measured
    before it) when it fails."""
    row = {}
    quick = bool(cfg.get("quick", False))
    try:
        mcfg = OmegaConf.create(OmegaConf.to_container(cfg.models[m], resolve=True))
        mcfg = model_config_for_neighbors(mcfg, hydra.utils.instantiate(cfg.neighbors), f"models.{m}")
        rps = cfg.bench.get("rays_per_step")
        if rps is not None and "rays_per_step" in mcfg:
            mcfg.rays_per_step = int(rps)
        if cfg.get("seed") is not None:
            L.seed_everything(int(cfg.seed), verbose=False)
        model = hydra.utils.instantiate(mcfg)
        row["method"] = model.method
        row["parameters"] = int(sum(p.numel() for p in model.parameters()))
        row["trainable_parameters"] = int(sum(p.numel() for p in model.parameters() if p.requires_grad))
        row["checkpoint_mb"] = round(checkpoint_mb(model), 3)
        model = model.to(device)
        row["samples_per_ray"] = samples_per_ray(model, infer[0])
        with autocast(cfg, device):
            compete = bool(cfg.bench.get("compete"))
            row.update(measure_inference(model, infer, device, light_warmup=quick, compete=compete))
            if row["trainable_parameters"]:
                row.update(measure_training(model, train, device, light_warmup=quick, compete=compete))
        if not row["trainable_parameters"]:
            row.update(dict.fromkeys(("train_s_per_step", "train_rays_per_step", "train_rays_per_s", "peak_mb_train")))
        row["disturbances"] = disturbances(row)
        row["disturbed"] = bool(row["disturbances"])
        peaks = [v for v in (row.get("peak_mb_train"), row.get("peak_mb_infer")) if v is not None]
        row["peak_mb"] = max(peaks) if peaks else None
        row["device"] = device.type
    except Exception as exc:
        log.exception("%s on %s failed; recorded with its error, going on with the others", m, scene_name)
        row["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        model = None
        release_memory()
    return row
