"""GRaF's training step, the grouped path against the static one, side by side in one run (scripts/gpu_check.sh's
``step_profile`` step).

    python scripts/gpu_step_profile.py OUT.json [--tiny] [bench overrides, e.g. data_root=...]

For each path (``grouped``: one group per voxel count, read on the host; ``static``: one group padded to the longest
ray, nothing read back: graf.models.graf.buckets), each precision (fp32; bf16 autocast) and each number of rays a
step (5,120, 20,480, 81,920: the paper's and 4x and 16x it), on paper-size GRaF (``model=graf``) and the simulated
conference_v1 (graf-bench's ``room``): ``WARMUP`` optimiser steps, then ``TIMED`` timed steps (median, spread:
(max - min) / median; ``trusted`` where the spread is at most ``TRUSTED_SPREAD``); then the operator calls and host
reads of one forward and backward, and on a CUDA device a whole step's kernel launches and the share of its wall
time the GPU was busy.  TF32 for fp32 matrix products on CUDA (trainer=gpu's ``float32_matmul_precision: high``).
``--tiny``: toy sizes on the embedded rfid_s23, 2 timed steps, on whatever device there is (a CPU in the tests).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import hydra
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from graf.app.config import CONF_DIR
from graf.studies.bench import prepare_scene
from graf.studies.bench_measure import optimizer_and_scheduler

WARMUP, TIMED, TRUSTED_SPREAD = 3, 20, 0.15
RAYS = (5120, 20480, 81920)
HOST_READS = ("aten::_local_scalar_dense", "aten::nonzero")  # .item() / bool() / int(), boolean indexing
TINY = [
    "models.graf.max_samples=2", "models.graf.encoder_widths=[4,8,8,8]", "models.graf.encoder_downsample=4",
]  # fmt: skip


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(model, batches, device, precision: str, timed: int) -> dict:
    model.train()
    model.log = lambda *a, **k: None
    opt, sched = optimizer_and_scheduler(model.configure_optimizers())  # the model's own (Adam, decayed)
    cast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")

    def forward_backward(i):
        with cast:
            loss = model.training_step(batches[i % len(batches)], i)
        loss.backward()

    def step(i):
        forward_backward(i)
        opt.step()
        opt.zero_grad(set_to_none=True)
        if sched is not None:
            sched.step()

    for i in range(WARMUP):
        step(i)
    times = []
    for i in range(timed):
        _sync(device)
        t = time.perf_counter()
        step(WARMUP + i)
        _sync(device)
        times.append(time.perf_counter() - t)
    # the model's forward and backward alone: its operators and its reads of a tensor's value on the host
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        forward_backward(0)
    opt.zero_grad(set_to_none=True)
    ev = prof.key_averages()
    med = statistics.median(times)
    spread = (max(times) - min(times)) / med if med else None
    row = {
        "s_per_step": round(med, 6),
        "times_s": [round(x, 6) for x in times],
        "spread": None if spread is None else round(spread, 3),
        "trusted": spread is not None and len(times) >= TIMED and spread <= TRUSTED_SPREAD,
        "rays_per_s": round(model.rays_per_step / med, 1),
        "operator_calls_per_step": sum(e.count for e in ev if e.key.startswith("aten::")),
        "host_reads_per_step": sum(e.count for e in ev if e.key in HOST_READS),
    }
    if device.type == "cuda":  # a whole optimiser step: kernel launches, and the GPU's busy share of its wall time
        acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        _sync(device)
        with torch.profiler.profile(activities=acts) as prof:
            t = time.perf_counter()
            step(0)
            _sync(device)
            wall = time.perf_counter() - t
        ev = prof.key_averages()
        row["kernel_launches_per_step"] = sum(e.count for e in ev if e.key.startswith("cudaLaunchKernel"))
        busy_us = sum(getattr(e, "self_device_time_total", 0) for e in ev if e.device_type.name == "CUDA")
        row["gpu_busy_fraction"] = round(busy_us / 1e6 / wall, 3)
        row["profiled_wall_s"] = round(wall, 6)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--tiny", action="store_true")
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.type == "cuda":
        torch.set_float32_matmul_precision("high")  # TF32, as trainer=gpu sets it
    scene = "real" if a.tiny else "room"
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("bench", overrides=[*(TINY if a.tiny else []), *a.overrides])
    timed = 2 if a.tiny else TIMED
    rays = (256, 512) if a.tiny else RAYS
    _, _, train, _ = prepare_scene(cfg, scene, 1, 3)
    out = {"device": torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu", "tiny": a.tiny, "rows": []}
    for precision in ("fp32", "bf16"):
        for path in ("grouped", "static"):
            for r in rays:
                torch.manual_seed(0)
                mcfg = OmegaConf.create(OmegaConf.to_container(cfg.models.graf, resolve=True))
                mcfg.rays_per_step = r
                model = hydra.utils.instantiate(mcfg).to(device)
                model.static_shapes = path == "static"
                moved = (model.on_before_batch_transfer(b, 0) for b in train)  # host-read keys first, as Lightning
                bs = [{k: v.to(device) if torch.is_tensor(v) else v for k, v in b.items()} for b in moved]
                row = {"precision": precision, "path": path, "rays_per_step": r, "scene": scene}
                try:
                    row.update(measure(model, bs, device, precision, timed))
                except Exception as e:  # a row that fails says why; the others still run
                    row["error"] = f"{type(e).__name__}: {e}"
                print(json.dumps(row), flush=True)
                out["rows"].append(row)
                del model
                if device.type == "cuda":
                    torch.cuda.empty_cache()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=2) + "\n")
    tmp.replace(a.out)


if __name__ == "__main__":
    main()
