"""graf-bench: the methods' cost side by side on a real and a simulated scene.

    graf-bench [quick=true] [threads=N] [bench.models=[knn,graf_cpu]] [bench.scenes=[real]] [data_root=DIR]

For every scene of ``scenes`` (default: ``real`` = the embedded rfid_s23 at 915 MHz, ``room`` = the
simulated conference_v1 at 2.4 GHz) and every model of ``models`` (default: ``graf``, ``graf_cpu``,
``nerf2``, ``nerf2_cpu``, ``knn_dl``, ``knn``: the model configs of those names) it measures, one row each:

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
  (``train_rays_per_step`` records the rays actually rendered); a model without one (KNN-DL) trains on
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

Everything runs on the GPU when ``torch.cuda.is_available()`` (``device_type``: ``cuda``; the table's first
line names the device), else on the CPU with ``threads`` threads (null: torch's default; recorded).

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

import ctypes
import gc
import logging
import math
import os
import platform
import statistics
import tempfile
import threading
import time
from pathlib import Path

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from graf.errors import ConfigError
from graf.io import atomic_write_bytes, atomic_write_json
from graf.run.build import build_datamodule
from graf.run.config import CONF_DIR, band_choices, output_dir, task_wrapper
from graf.sim_commands.simulate import simulate

log = logging.getLogger("graf")

N_RAYS = 90 * 360  # rays (pixels) of one spectrum
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
)
GRAF_METHODS = ("graf", "graf-residual")
BASE_PRESET = "graf"
LIGHT_WARMUP_RAYS = 256  # rays of quick=true's warm-up training step
WARMUP = {
    "whole": "one whole spectrum before the timed ones; one whole training step before the timed ones",
    "light": "quick: one chunk of chunk_rays rays (GRaF, NeRF2; a whole spectrum for the others) before the "
    "timed spectrum; one training step at 256 rays (models with rays_per_step) before the timed one",
}


# ---------------------------------------------------------------------------------------------- machine
def device_name(device: torch.device) -> str:
    """The CUDA device's name, or the CPU's model name from /proc/cpuinfo."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, device: torch.device) -> float:
    """Seconds of one call of ``fn`` (CUDA: synchronised before and after)."""
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t0


_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_bytes() -> int | None:
    """The process's current resident set size (Linux: /proc/self/statm; else psutil if installed)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        try:
            import psutil

            return int(psutil.Process().memory_info().rss)
        except Exception:
            return None


def _release_memory() -> None:
    """Collect garbage and hand freed heap back to the OS (glibc), so a phase starts from what is live."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class PeakMemory:
    """Peak memory of a phase above its start, in MiB (``.mb``; None where it cannot be measured).

    CPU: resident set size sampled every ``interval`` s by a thread.  CUDA: ``max_memory_allocated`` after
    ``reset_peak_memory_stats``, minus the memory allocated at the start."""

    def __init__(self, device: torch.device, interval: float = 0.005):
        self.device, self.interval = device, float(interval)
        self.mb: float | None = None

    def __enter__(self):
        _release_memory()
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._start = torch.cuda.memory_allocated(self.device)
            return self
        self._start = rss_bytes()
        self._peak = self._start
        self._stop = threading.Event()
        if self._start is not None:
            self._thread = threading.Thread(target=self._poll, name="graf-bench-rss", daemon=True)
            self._thread.start()
        return self

    def _poll(self) -> None:
        while not self._stop.wait(self.interval):
            r = rss_bytes()
            if r is not None and r > self._peak:
                self._peak = r

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.mb = (torch.cuda.max_memory_allocated(self.device) - self._start) / 2**20
            return False
        if self._start is None:
            return False
        self._stop.set()
        self._thread.join()
        r = rss_bytes()
        self._peak = max(self._peak, r if r is not None else 0)
        self.mb = max(0, self._peak - self._start) / 2**20
        return False


def memory_method(device: torch.device) -> str:
    if device.type == "cuda":
        return (
            "cuda: torch.cuda.max_memory_allocated() after reset_peak_memory_stats(), minus the memory "
            "allocated at the phase's start (MiB)"
        )
    return (
        "cpu: peak resident set size during the phase (sampled every 5 ms) minus the resident set size at "
        "its start (MiB)"
    )


# ---------------------------------------------------------------------------------------------- model pieces
def checkpoint_mb(model) -> float:
    """Size of a weights-only Lightning checkpoint of ``model``, in MiB."""
    quiet = logging.getLogger("lightning.pytorch")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # no "GPU available: ..." banner per row
    try:
        return _checkpoint_mb(model)
    finally:
        quiet.setLevel(level)


def _checkpoint_mb(model) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        trainer = L.Trainer(
            accelerator="cpu",
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
            max_steps=0,
        )
        trainer.strategy.connect(model)
        path = Path(tmp) / "m.ckpt"
        trainer.save_checkpoint(path, weights_only=True)
        return path.stat().st_size / 2**20


def samples_per_ray(model, batch: dict) -> float | int | None:
    """Mean voxels per ray where the model reports it (GRaF), else its samples per ray (NeRF2); None for
    models that do not render rays."""
    if hasattr(model, "mean_samples_per_ray"):
        return round(float(model.mean_samples_per_ray(batch)[0]), 2)
    if hasattr(model, "samples_per_ray"):
        return int(model.samples_per_ray(batch)[0])
    return None


def optimizer_and_scheduler(conf):
    """``(optimizer, scheduler or None)`` from whatever ``configure_optimizers`` returned (an optimiser, a
    dict, a list or tuple of either, or ``([optimisers], [schedulers])``); the first optimiser is used."""
    if isinstance(conf, torch.optim.Optimizer):
        return conf, None
    if isinstance(conf, dict):
        sched = conf.get("lr_scheduler")
        if isinstance(sched, dict):
            sched = sched.get("scheduler")
        return conf["optimizer"], sched
    if isinstance(conf, (list, tuple)) and conf:
        if len(conf) == 2 and isinstance(conf[0], (list, tuple)):
            opts, scheds = conf
            sched = scheds[0] if scheds else None
            if isinstance(sched, dict):
                sched = sched.get("scheduler")
            return opts[0], sched
        return optimizer_and_scheduler(conf[0])
    raise TypeError(f"configure_optimizers returned {type(conf).__name__}: no optimiser to step")


def rays_per_train_step(model, batch_size: int) -> int:
    """Rays one training step renders: ``rays_per_step // B`` per target (at most a whole spectrum) where
    the model has that setting, else whole spectra."""
    rps = getattr(model, "rays_per_step", None)
    if rps is None:
        return N_RAYS * batch_size
    return min(N_RAYS, max(1, int(rps) // batch_size)) * batch_size


def _to(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}


def _median(xs: list[float]) -> float | None:
    return round(float(statistics.median(xs)), 6) if xs else None


def warm_up_inference(model, batch: dict, light: bool) -> None:
    """A whole spectrum; ``light`` (quick=true): one chunk of ``chunk_rays`` rays through the model's own
    ``prepare`` and ``render`` where it has them (GRaF, NeRF2; neighbor encodings and ray tables are made
    and cached as by a whole spectrum), a whole spectrum otherwise."""
    if light and hasattr(model, "prepare") and hasattr(model, "render"):
        ctx = model.prepare(batch)
        B = int(batch["tgt_pos"].shape[0])
        n = min(N_RAYS, max(1, int(getattr(model, "chunk_rays", 1024)) // B))
        model.render(ctx, torch.arange(n, device=batch["tgt_pos"].device)[None].expand(B, -1))
    else:
        model.predict_spectra(batch)


def measure_inference(model, batches: list[dict], device: torch.device, light_warmup: bool = False) -> dict:
    """Warm-up on ``batches[0]``, then each later batch timed on its own; median seconds and peak memory."""
    model.eval()
    with torch.no_grad(), PeakMemory(device) as mem:
        warm_up_inference(model, batches[0], light_warmup)
        times = [_timed(lambda b=b: model.predict_spectra(b), device) for b in batches[1:]]
    return {
        "infer_s_per_spectrum": _median(times),
        "infer_times_s": [round(t, 6) for t in times],
        "peak_mb_infer": None if mem.mb is None else round(mem.mb, 1),
    }


def measure_training(model, batches: list[dict], device: torch.device, light_warmup: bool = False) -> dict:
    """One warm-up optimiser step on ``batches[0]`` (``light``: at ``LIGHT_WARMUP_RAYS`` rays where the model
    has a ``rays_per_step`` setting), then one timed step per later batch (see module doc)."""
    model.train()
    model.log = lambda *args, **kwargs: None  # no Trainer: Lightning's log would only warn
    with PeakMemory(device) as mem:
        opt, sched = optimizer_and_scheduler(model.configure_optimizers())

        def step(batch, i):
            loss = model.training_step(batch, i)
            loss.backward()
            opt.step()
            opt.zero_grad(set_to_none=True)
            if sched is not None:
                sched.step()

        rays = getattr(model, "rays_per_step", None)
        if light_warmup and rays is not None:
            model.rays_per_step = min(int(rays), LIGHT_WARMUP_RAYS)
        try:
            step(batches[0], 0)
        finally:
            if rays is not None:
                model.rays_per_step = rays
        times = [_timed(lambda b=b, i=i: step(b, i), device) for i, b in enumerate(batches[1:], start=1)]
    opt = sched = None  # the optimiser state is released before the next measurement
    B = int(batches[0]["tgt_pos"].shape[0])
    rays = rays_per_train_step(model, B)
    s = _median(times)
    return {
        "train_s_per_step": s,
        "train_times_s": [round(t, 6) for t in times],
        "train_batch_size": B,
        "train_rays_per_step": rays,
        "train_rays_per_s": round(rays / s, 1) if s else None,
        "peak_mb_train": None if mem.mb is None else round(mem.mb, 1),
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
    bands, _, _, dm = build_datamodule(dcfg)
    band = bands[0]
    dm.setup("fit")
    idx, mask = dm.eval_neighbors()
    rows = dm.eval_rows[: spectra + 1]
    infer = [dm.make_batch(rows[i : i + 1], idx[i : i + 1], mask[i : i + 1]) for i in range(len(rows))]
    train = [dm.train_batch(k) for k in range(train_steps + 1)]
    return dm, infer, train, band.name


# ---------------------------------------------------------------------------------------------- report
def add_ratios(rows: list[dict]) -> dict:
    """Fill each row's ratios to its scene's ratio base (module doc); returns ``{scene: base preset}``."""
    bases = {}
    for r in rows:
        s = r["scene"]
        if s in bases:
            continue
        ok = [x for x in rows if x["scene"] == s and not x.get("error") and x.get("infer_s_per_spectrum")]
        base = next((x for x in ok if x["preset"] == BASE_PRESET), None) or next(
            (x for x in ok if x["method"] in GRAF_METHODS), None
        )
        bases[s] = base
    for r in rows:
        base = bases[r["scene"]]
        for key, ratio in (
            ("infer_s_per_spectrum", "infer_ratio_to_graf"),
            ("train_s_per_step", "train_ratio_to_graf"),
        ):
            v, b = r.get(key), (base or {}).get(key)
            r[ratio] = round(v / b, 4) if v is not None and b and not r.get("error") else None
    return {s: (b["preset"] if b else None) for s, b in bases.items()}


def _f(v, spec: str = ".4g", none: str = "-") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return none
    return format(v, spec)


def markdown(result: dict) -> str:
    """The table of ``result["rows"]`` with a line on how it was measured."""
    head = (
        f"graf-bench on {result['device']} ({result['device_type']}, {result['threads']} threads, torch "
        f"{result['torch']}): median of {result['spectra_timed']} spectra and of {result['train_steps_timed']} "
        f"training steps (warm-up: {result['warmup']}); peak memory: {result['memory']}; "
        "ratios: to the scene's GRaF row (paper size where present)."
    )
    cols = [
        "scene",
        "preset",
        "method",
        "samples/ray",
        "s/spectrum",
        "× GRaF",
        "s/step",
        "rays/step",
        "rays/s",
        "× GRaF",
        "peak MB train",
        "peak MB infer",
        "parameters",
        "checkpoint MB",
    ]
    lines = [head, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in result["rows"]:
        if r.get("error"):
            cells = [r["scene"], r["preset"], r.get("method") or "-", f"error: {r['error']}"] + [""] * (len(cols) - 4)
        else:
            cells = [
                r["scene"],
                r["preset"],
                r["method"],
                _f(r["samples_per_ray"], "g"),
                _f(r["infer_s_per_spectrum"]),
                _f(r["infer_ratio_to_graf"], ".3g"),
                _f(r["train_s_per_step"]),
                _f(r.get("train_rays_per_step"), ","),
                _f(r["train_rays_per_s"], ",.0f"),
                _f(r["train_ratio_to_graf"], ".3g"),
                _f(r["peak_mb_train"], ".1f"),
                _f(r["peak_mb_infer"], ".1f"),
                _f(r["parameters"], ","),
                _f(r["checkpoint_mb"], ".2f"),
            ]
        lines.append("| " + " | ".join(str(c).replace("|", "/") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _write(out: Path, result: dict) -> None:
    result["ratio_base"] = add_ratios(result["rows"])
    atomic_write_json(out / "results.json", result)
    atomic_write_bytes(out / "bench.md", markdown(result).encode())


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
    if cfg.get("threads") is not None:
        torch.set_num_threads(int(cfg.threads))
    quick = bool(cfg.get("quick", False))
    spectra = 1 if quick else int(cfg.bench.spectra)
    steps = 1 if quick else int(cfg.bench.train_steps)
    if spectra < 1 or steps < 1:
        raise ConfigError("bench.spectra and bench.train_steps must be at least 1")
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
        "memory": memory_method(device),
        "ratio_base": {},
        "rows": [],
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    rows = result["rows"]
    rps = cfg.bench.get("rays_per_step")
    skip = set(cfg.bench.get("quick_skip") or []) if quick else set()
    result["skipped"] = [f"{k}/{m}" for k in scene_keys for m in model_keys if f"{k}/{m}" in skip]
    for key in scene_keys:
        started = time.perf_counter()
        try:
            dm, infer, train, band_name = prepare_scene(cfg, key, spectra, steps)
            scene_name = dm.data.name
            infer = [_to(b, device) for b in infer]
            train = [_to(b, device) for b in train]
        except Exception as exc:
            log.exception("scene %s: could not prepare its data; its rows record the error", key)
            name = cfg.scenes[key].get("name", key)
            for m in model_keys:
                rows.append(
                    {
                        **dict.fromkeys(ROW_KEYS),
                        "scene": name,
                        "scene_key": key,
                        "preset": m,
                        "error": f"{type(exc).__name__}: {exc}",
                        "seconds": round(time.perf_counter() - started, 3),
                    }
                )
            _write(out, result)
            continue
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
            try:
                mcfg = OmegaConf.create(OmegaConf.to_container(cfg.models[m], resolve=True))
                if rps is not None and "rays_per_step" in mcfg:
                    mcfg.rays_per_step = int(rps)
                if cfg.get("seed") is not None:
                    L.seed_everything(int(cfg.seed), verbose=False)
                model = hydra.utils.instantiate(mcfg)
                row["method"] = getattr(model, "method", m)
                row["parameters"] = int(sum(p.numel() for p in model.parameters()))
                row["trainable_parameters"] = int(sum(p.numel() for p in model.parameters() if p.requires_grad))
                row["checkpoint_mb"] = round(checkpoint_mb(model), 3)
                model = model.to(device)
                row["samples_per_ray"] = samples_per_ray(model, infer[0])
                row.update(measure_inference(model, infer, device, light_warmup=quick))
                if row["trainable_parameters"]:
                    row.update(measure_training(model, train, device, light_warmup=quick))
                else:
                    row.update(
                        {
                            "train_s_per_step": None,
                            "train_rays_per_step": None,
                            "train_rays_per_s": None,
                            "peak_mb_train": None,
                        }
                    )
                peaks = [v for v in (row.get("peak_mb_train"), row.get("peak_mb_infer")) if v is not None]
                row["peak_mb"] = max(peaks) if peaks else None
                row["device"] = device.type
            except Exception as exc:
                log.exception("%s on %s failed; recorded with its error, going on with the others", m, scene_name)
                row["error"] = f"{type(exc).__name__}: {exc}"
            finally:
                model = None
                _release_memory()
            row["seconds"] = round(time.perf_counter() - started, 3)
            rows.append({**dict.fromkeys(ROW_KEYS), **row})
            _write(out, result)
            log.info(
                "%s on %s: %s",
                m,
                scene_name,
                "error"
                if row.get("error")
                else f"{_f(row['infer_s_per_spectrum'])} s/spectrum, {_f(row['train_s_per_step'])} s/step",
            )
    _write(out, result)
    print(markdown(result))
    log.info("results: %s", out / "results.json")
    return result
