"""graf-bench-sim: how fast the simulator makes spectra here, and whether its sample budget converged.

    graf-bench-sim scene=conference_v1 band=2.4ghz [bench.num_tx=512] [bench.convergence_tx=64]

Prints and writes (results.json) the one-off set-up and JIT time, steady-state spectra per second end to
end (tracing + Bartlett + 8-bit quantisation) and per stage, the ratio to the paper's 59.5 s per
spectrum (MATLAB ray tracing), and, for ``convergence_tx`` positions, the PSNR between the scene's
default sample budget and twice that budget.
"""

from __future__ import annotations

import os
import platform
import time

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from graf.app.config import output_dir, scene_band_config, task_wrapper
from graf.app.spec import RunSpec
from graf.io import atomic_write_json
from graf.metrics import psnr_per_sample
from graf.sim.array import to_uint8
from graf.sim.tracer import spectra_from_paths

PAPER_SECONDS_PER_SPECTRUM = 59.5


def _cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


@task_wrapper
def bench(cfg: DictConfig) -> dict:
    scene_cfg = RunSpec.of(cfg).one_scene("graf-bench-sim")
    band = hydra.utils.instantiate(scene_band_config(scene_cfg, cfg.get("band")))
    scene = hydra.utils.instantiate(scene_cfg)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    n = int(cfg.bench.num_tx)
    spc = int(scene.tracing.get("sources_per_call", 256))
    positions = scene.positions(min(n + spc, int(scene.transmitters["count"])))
    t0 = time.perf_counter()
    tracer = scene.tracer(band)
    bart = scene.bartlett(band, device=device)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    tracer.trace(positions[:spc])  # first call: JIT compilation
    t_first = time.perf_counter() - t0
    steady = positions[spc : spc + n] if len(positions) > spc else positions[:n]
    out = {
        "scene": scene.name,
        "band": band.name,
        "band_hz": band.frequency_hz,
        **steady_state(scene, tracer, bart, steady, spc, device, t_build, t_first),
        "tracing": dict(scene.tracing),
    }
    k = int(cfg.bench.convergence_tx)
    if k > 0:
        out["convergence"] = convergence(scene, band, tracer, bart, positions[:k])
    out["config"] = OmegaConf.to_container(cfg, resolve=True)
    atomic_write_json(output_dir(cfg) / "results.json", out)
    print_bench(out, t_build, t_first)
    return out


def steady_state(scene, tracer, bart, steady, spc: int, device: str, t_build: float, t_first: float) -> dict:
    """Spectra per second end to end and per stage (tracing, Bartlett, quantisation) over the positions
    ``steady``, ``spc`` at a time, with the machine and the one-off times (set-up ``t_build``, first call
    ``t_first``)."""
    t_trace = t_bart = t_q = 0.0
    path_counts = []
    for s in range(0, len(steady), spc):
        t0 = time.perf_counter()
        g, d, c = tracer.trace(steady[s : s + spc])
        path_counts.append(c)
        t1 = time.perf_counter()
        h, spectra = spectra_from_paths(bart, g, d, scene.array.get("pattern", "cos"))
        if device == "cuda":
            torch.cuda.synchronize()
        t2 = time.perf_counter()
        to_uint8(spectra)
        t3 = time.perf_counter()
        t_trace, t_bart, t_q = t_trace + t1 - t0, t_bart + t2 - t1, t_q + t3 - t2
    m = len(steady)
    total = t_trace + t_bart + t_q
    return {
        "positions": m,
        "machine": {
            "cpu": _cpu_name(),
            "threads": torch.get_num_threads(),
            "cores": os.cpu_count(),
            "gpu": torch.cuda.get_device_name(0) if device == "cuda" else None,
        },
        "setup_seconds": round(t_build, 3),
        "first_call_seconds": round(t_first, 3),
        "spectra_per_second": round(m / total, 2),
        "ms_per_spectrum": {
            "trace": round(1e3 * t_trace / m, 3),
            "bartlett": round(1e3 * t_bart / m, 3),
            "quantise": round(1e3 * t_q / m, 3),
            "total": round(1e3 * total / m, 3),
        },
        "speedup_vs_paper_matlab": round(PAPER_SECONDS_PER_SPECTRUM / (total / m), 1),
        "paths_per_position": {
            "mean": round(float(np.mean(np.concatenate(path_counts))), 2),
            "fraction_without_paths": round(float(np.mean(np.concatenate(path_counts) == 0)), 4),
        },
    }


def convergence(scene, band, tracer, bart, pos) -> dict:
    """PSNR of the spectra at ``pos`` between the scene's sample budget and twice that budget."""
    base = scene.spectra(tracer, bart, pos)[1]
    doubled = {
        "samples_per_src": 2 * int(scene.tracing["samples_per_src"]),
        "max_num_paths_per_src": 2 * int(scene.tracing["max_num_paths_per_src"]),
    }
    ref = scene.spectra(scene.tracer(band, **doubled), bart, pos)[1]
    p = psnr_per_sample(base.cpu(), ref.cpu())
    return {
        "positions": len(pos),
        "samples_per_src": [int(scene.tracing["samples_per_src"]), doubled["samples_per_src"]],
        "psnr_min": round(float(p.min()), 2),
        "psnr_median": round(float(p.median()), 2),
        "fraction_under_40db": round(float((p < 40).float().mean()), 4),
    }


def print_bench(out: dict, t_build: float, t_first: float) -> None:
    """The benchmark's lines on the terminal (``t_build``, ``t_first``: the set-up and first call, unrounded)."""
    mach = out["machine"]
    print(f"graf-bench-sim {out['scene']} {out['band']} on {mach['gpu'] or mach['cpu']} ({mach['threads']} threads)")
    print(f"  set-up {t_build:.2f} s, first call (JIT) {t_first:.2f} s")
    ms = out["ms_per_spectrum"]
    print(
        f"  steady state over {out['positions']} positions: {out['spectra_per_second']:.1f} spectra/s "
        f"(trace {ms['trace']:.2f} ms + Bartlett {ms['bartlett']:.3f} ms + quantise {ms['quantise']:.3f} ms)"
    )
    pp = out["paths_per_position"]
    print(
        f"  {pp['mean']:.1f} traced paths per position; {100 * pp['fraction_without_paths']:.1f}% of "
        f"positions without any"
    )
    print(f"  vs the paper's MATLAB ray tracing, 59.5 s per spectrum: {out['speedup_vs_paper_matlab']:.0f}x faster")
    if "convergence" in out:
        c = out["convergence"]
        print(
            f"  convergence, {c['samples_per_src'][0]} vs {c['samples_per_src'][1]} samples per source on "
            f"{c['positions']} positions: PSNR min {c['psnr_min']:.1f} dB, median {c['psnr_median']:.1f} dB, "
            f"{100 * c['fraction_under_40db']:.1f}% under 40 dB"
        )
