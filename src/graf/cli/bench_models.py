"""graf-bench-models: model cost side by side (parameters, checkpoint size, inference time per spectrum).

    graf-bench-models [scene=rfid_s23] [bench.spectra=3]

Each method predicts the same test spectra (the first ``bench.spectra`` of the scene's test split, one
at a time after one warm-up); prints a table with ratios to the first model and writes results.json.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from graf.cli.common import CONF_PATH, _output_dir, build_datamodule, task_wrapper
from graf.io import atomic_write_json

PAPER = {"graf": {"mb": 478.6, "s_per_spectrum": 1.95}, "nerf2": {"mb": 8.3, "s_per_spectrum": 0.43}}


def _samples(model, batch):
    """Samples per ray of a ray-rendering model (GRaF, NeRF2) on this scene and band; None for the others."""
    return int(model.samples_per_ray(batch)[0]) if hasattr(model, "samples_per_ray") else None


@task_wrapper
def bench(cfg: DictConfig) -> dict:
    band, scene, neighbors, dm = build_datamodule(cfg)
    dm.setup("test")
    n = int(cfg.bench.spectra)
    idx, mask = dm.eval_neighbors()
    rows = dm.eval_rows[: n + 1]
    batches = [dm.make_batch(rows[i:i + 1], idx[i:i + 1], mask[i:i + 1]) for i in range(len(rows))]
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    batches = [{k: v.to(device) for k, v in b.items()} for b in batches]
    out = {}
    for name, mcfg in cfg.models.items():
        model = hydra.utils.instantiate(mcfg).to(device).eval()
        params = sum(p.numel() for p in model.parameters())
        with tempfile.TemporaryDirectory() as tmp:
            trainer = L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                                enable_model_summary=False, max_steps=0)
            trainer.strategy.connect(model)
            path = Path(tmp) / "m.ckpt"
            trainer.save_checkpoint(path, weights_only=True)
            mb = path.stat().st_size / 2 ** 20
        with torch.no_grad():
            model.predict_spectra(batches[0])  # warm-up
            if device.type == "cuda":
                torch.cuda.synchronize()  # the warm-up's kernels must not run into the timed window
            t0 = time.perf_counter()
            for b in batches[1:]:
                model.predict_spectra(b)
            if device.type == "cuda":
                torch.cuda.synchronize()
            sec = (time.perf_counter() - t0) / max(len(batches) - 1, 1)
        out[name] = {"method": getattr(model, "method", name), "parameters": int(params),
                     "checkpoint_mb": round(mb, 2), "s_per_spectrum": round(sec, 3),
                     "samples_per_ray": _samples(model, batches[0])}
    first = next(iter(out.values()))
    result = {"scene": dm.data.name, "device": torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu",
              "threads": torch.get_num_threads(), "spectra_timed": len(batches) - 1, "models": out, "paper": PAPER,
              "config": OmegaConf.to_container(cfg, resolve=True)}
    atomic_write_json(_output_dir(cfg) / "results.json", result)
    print(f"on {result['device']} ({result['threads']} threads), scene {dm.data.name}, L = {neighbors.L}:")
    print(f"{'model':<14}{'parameters':>12}{'ckpt MB':>10}{'s/spectrum':>12}{'time ratio':>12}")
    for name, r in out.items():
        ratio = r["s_per_spectrum"] / first["s_per_spectrum"] if first["s_per_spectrum"] else float("nan")
        print(f"{name:<14}{r['parameters']:>12,}{r['checkpoint_mb']:>10.2f}{r['s_per_spectrum']:>12.3f}{ratio:>12.2f}")
    print("paper (GPU): GRaF 478.6 MB, 1.95 s/spectrum; NeRF2 8.3 MB, 0.43 s/spectrum")
    return result


@hydra.main(version_base="1.3", config_path=CONF_PATH, config_name="bench_models")
def main(cfg: DictConfig) -> None:
    bench(cfg)


if __name__ == "__main__":
    main()
