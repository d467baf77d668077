"""graf-bench's measurements of one model: seconds per spectrum and per training step, peak memory, size
(the definitions are graf.studies.bench's module doc)."""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import platform
import statistics
import tempfile
import threading
import time
from pathlib import Path

import lightning as L
import torch

from graf.studies.bench_load import Competitor, LoadMeter, spread

N_RAYS = 90 * 360  # rays (pixels) of one spectrum
LIGHT_WARMUP_RAYS = 256  # rays of quick=true's warm-up training step


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
            import psutil  # here: an optional package, needed only where /proc is not

            return int(psutil.Process().memory_info().rss)
        except Exception:
            return None


def release_memory() -> None:
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
        release_memory()
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
    """How :class:`PeakMemory` measures on ``device``, in words (results.json's ``memory``)."""
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


def samples_per_ray(model, batch: dict) -> float | None:
    """Mean samples (voxels) per ray of the batch's first item (:meth:`graf.models.base.Method.mean_samples_per_ray`);
    None for methods that render no rays."""
    mean = model.mean_samples_per_ray(batch)
    return None if mean is None else round(float(mean[0]), 2)


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
    rps = model.rays_per_step
    if rps is None:
        return N_RAYS * batch_size
    return min(N_RAYS, max(1, int(rps) // batch_size)) * batch_size


def to_device(batch: dict, device: torch.device) -> dict:
    """The batch with its tensors on ``device``."""
    return {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}


def _median(xs: list[float]) -> float | None:
    return round(float(statistics.median(xs)), 6) if xs else None


def warm_up_inference(model, batch: dict, light: bool) -> None:
    """A whole spectrum; ``light`` (quick=true): one chunk of ``chunk_rays`` rays through the model's own
    ``prepare`` and ``render`` where it has them (GRaF, NeRF2; neighbor encodings and ray tables are made
    and cached as by a whole spectrum), a whole spectrum otherwise."""
    if light and model.renders_rays:
        ctx = model.prepare(batch)
        B = int(batch["tgt_pos"].shape[0])
        n = min(N_RAYS, max(1, int(model.chunk_rays or N_RAYS * B) // B))
        model.render(ctx, torch.arange(n, device=batch["tgt_pos"].device)[None].expand(B, -1))
    else:
        model.predict_spectra(batch)


def _timed_spectra(
    model, batches: list[dict], device: torch.device, light_warmup: bool
) -> tuple[list[float], LoadMeter]:
    """The warm-up on ``batches[0]``, then each later batch timed on its own (the load measured meanwhile)."""
    warm_up_inference(model, batches[0], light_warmup)
    with LoadMeter() as load:
        times = [_timed(lambda b=b: model.predict_spectra(b), device) for b in batches[1:]]
    return times, load


def measure_inference(
    model, batches: list[dict], device: torch.device, light_warmup: bool = False, compete: bool = False
) -> dict:
    """Warm-up on ``batches[0]``, then each later batch timed on its own; median seconds, peak memory, the other
    processes' load and the spread of the timings.  ``compete``: then again (the model's evaluation caches
    emptied, the warm-up repeated) beside a competing process (:class:`Competitor`), and the slowdown."""
    model.eval()
    with torch.no_grad(), PeakMemory(device) as mem:
        times, load = _timed_spectra(model, batches, device, light_warmup)
    out = {
        "infer_s_per_spectrum": _median(times),
        "infer_times_s": [round(t, 6) for t in times],
        "infer_load_cores": load.cores,
        "infer_spread": spread(times),
        "peak_mb_infer": None if mem.mb is None else round(mem.mb, 1),
    }
    if compete:
        cache = getattr(model, "eval_cache", None)
        if cache is not None:
            cache.clear()
        with torch.no_grad(), Competitor():
            loaded, load = _timed_spectra(model, batches, device, light_warmup)
        out["infer_s_per_spectrum_loaded"] = _median(loaded)
        out["infer_times_s_loaded"] = [round(t, 6) for t in loaded]
        out["infer_load_cores_loaded"] = load.cores
        out["infer_slowdown"] = round(_median(loaded) / _median(times), 3) if times and _median(times) else None
    return out


def measure_training(
    model, batches: list[dict], device: torch.device, light_warmup: bool = False, compete: bool = False
) -> dict:
    """One warm-up optimiser step on ``batches[0]`` (``light``: at ``LIGHT_WARMUP_RAYS`` rays where the model
    has a ``rays_per_step`` setting), then one timed step per later batch (see module doc).  ``compete``: the
    later batches' steps timed again beside a competing process (:class:`Competitor`), and the slowdown."""
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

        rays = model.rays_per_step
        if light_warmup and rays is not None:
            model.rays_per_step = min(int(rays), LIGHT_WARMUP_RAYS)
        try:
            step(batches[0], 0)
        finally:
            if rays is not None:
                model.rays_per_step = rays
        with LoadMeter() as load:
            times = [_timed(lambda b=b, i=i: step(b, i), device) for i, b in enumerate(batches[1:], start=1)]
        loaded = None
        if compete:
            with Competitor(), LoadMeter() as loaded_load:
                loaded = [_timed(lambda b=b, i=i: step(b, i), device) for i, b in enumerate(batches[1:], start=1)]
    opt = sched = None  # the optimiser state is released before the next measurement
    B = int(batches[0]["tgt_pos"].shape[0])
    rays = rays_per_train_step(model, B)
    s = _median(times)
    return {
        "train_s_per_step": s,
        "train_times_s": [round(t, 6) for t in times],
        "train_load_cores": load.cores,
        "train_spread": spread(times),
        "train_batch_size": B,
        "train_rays_per_step": rays,
        "train_rays_per_s": round(rays / s, 1) if s else None,
        "peak_mb_train": None if mem.mb is None else round(mem.mb, 1),
        **(
            {}
            if loaded is None
            else {
                "train_s_per_step_loaded": _median(loaded),
                "train_times_s_loaded": [round(t, 6) for t in loaded],
                "train_load_cores_loaded": loaded_load.cores,
                "train_slowdown": round(_median(loaded) / s, 3) if s else None,
            }
        ),
    }
