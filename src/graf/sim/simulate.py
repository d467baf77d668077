"""graf-simulate: ray-trace a scene's transmitter positions at a band into a dataset file.

    graf-simulate scene=conference_v1 band=2.4ghz [sim.num_tx=64] [sim.export=nerf2] data_root=DIR
    graf-simulate -m scene=conference_v1 sim.shard.count=4 'sim.shard.index=range(4)'    # in shards (any launcher)
    graf-simulate scene=conference_v1 sim.merge=true                                     # assemble explicitly

Resumable (each shard on its own): kill it and run the same command again.  Writes results.json (spectra per
second, file, shard).
"""

from __future__ import annotations

import logging
import time

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from graf.app.config import output_dir, scene_band_config, task_wrapper
from graf.app.spec import RunSpec
from graf.errors import ConfigError
from graf.io import atomic_write_json, writable_dir
from graf.sim.dataset import export_nerf2, generate
from graf.sim.scene import SimulatedScene

log = logging.getLogger("graf")


@task_wrapper
def simulate(cfg: DictConfig) -> dict:
    started = time.perf_counter()
    scene_cfg = RunSpec.of(cfg).one_scene("graf-simulate")
    band = hydra.utils.instantiate(scene_band_config(scene_cfg, cfg.get("band")))
    scene = hydra.utils.instantiate(scene_cfg)
    if not isinstance(scene, SimulatedScene):
        raise ConfigError(
            f"scene {getattr(scene, 'name', scene_cfg.get('name'))} is not a simulated scene: graf-simulate "
            "needs a scene config with _target_: graf.sim.scene.SimulatedScene"
        )
    sim = cfg.sim
    if sim.export not in (None, "none", "nerf2"):
        raise ConfigError(f"sim.export must be null or 'nerf2', got {sim.export!r}")
    writable_dir(cfg.data_root, "data_root")  # before any tracing: a long run must not fail at its first write
    device = sim.device if sim.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    summary = generate(
        scene,
        band,
        cfg.data_root,
        num_tx=sim.num_tx,
        chunk_size=int(sim.chunk_size),
        overwrite=bool(sim.overwrite),
        device=device,
        progress=bool(sim.progress),
        shard=(int(sim.shard.index), int(sim.shard.count)),
        merge_only=bool(sim.merge),
    )
    if sim.export == "nerf2" and (summary.get("assembled") or summary.get("skipped")):
        folder = export_nerf2(summary["path"], summary["path"].replace(".h5", "_nerf2"))
        summary["nerf2_folder"] = str(folder)
    results = {
        "scene": scene.name,
        "band": band.name,
        "band_hz": band.frequency_hz,
        **summary,
        "device": device,
        "command_seconds": round(time.perf_counter() - started, 3),
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    atomic_write_json(output_dir(cfg) / "results.json", results)
    rate = summary.get("spectra_per_second")
    made = f"; made {summary['made']} at {rate:.1f} spectra/s" if rate else ""
    if summary.get("skipped") or summary.get("assembled"):
        print(f"{scene.name} {band.name}: {summary['n']} spectra in {summary['path']}" + (made or " (already there)"))
    else:  # a shard whose file waits for the others
        lo, hi = summary["shard_positions"] or (0, 0)
        print(
            f"{scene.name} {band.name}: shard {summary['shard'][0]} of {summary['shard'][1]} (positions {lo}-{hi - 1})"
            f" done{made}; {summary['missing_chunks']} chunks of other shards still missing: the last shard to "
            "finish assembles the file (or sim.merge=true)"
        )
    return results
