"""graf-synthesize: spectra at new transmitter positions from a checkpoint, as a NeRF2-format folder.

    graf-synthesize ckpt_path=RUN/checkpoints/last.ckpt model=graf_cpu scene=rfid_s23 positions=new.csv [out=DIR]
    graf-synthesize model=knn scene=rfid_s23 positions=new.csv        (a method with nothing trained)

``positions`` is a CSV of x,y,z (header optional).  Neighbors come from the scene's training split.
The folder (``<output_dir>/synthesized`` unless ``out``) holds spectrum/NNNNN.png, tx_pos.csv and
gateway_info.yml (no index files: a user splits synthesized data as the study needs); results.json
records the count and the time per spectrum.

Also the library call behind it (the paper's use: more spectra for training localization models)::

    from graf.case_studies.synthesis import synthesize
    spectra = synthesize(model, datamodule, positions)        # [N, 90, 360] in [0, 1]
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from graf.app.config import output_dir, task_wrapper
from graf.app.spec import RunSpec
from graf.data.nerf2_files import read_positions
from graf.data.nerf2_format import write_nerf2_folder
from graf.data.spectrum_set import DataFormatError
from graf.errors import ConfigError
from graf.geometry.grid import SPECTRUM_SHAPE
from graf.io import atomic_write_json
from graf.models.base import check_checkpoint, read_checkpoint, safe_loading
from graf.run.build import build_datamodule, model_config_for_neighbors


def read_query_positions(path: Path):
    """The query positions ``[N, 3]`` (x,y,z; header optional) and whether a header was found: at least one,
    every one finite, or a :class:`DataFormatError` naming the file and line."""
    positions, had_header = read_positions(path)
    if len(positions) == 0:
        raise DataFormatError(
            path, "holds no positions (a header row alone): give one x,y,z row per spectrum to synthesize"
        )
    bad = ~np.isfinite(positions).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise DataFormatError(
            path, f"data row {i + 1}: position {positions[i].tolist()} is not finite ({int(bad.sum())} such row(s))"
        )
    return positions, had_header


def _model_choice() -> str:
    return str(HydraConfig.get().runtime.choices.get("model")) if HydraConfig.initialized() else "..."


def load_model(model_cfg: DictConfig, ckpt_path: str | None, what: str | None = None):
    """The model of ``model_cfg`` (its ``_target_``), with the weights of ``ckpt_path`` (checked against the class
    first); without a checkpoint only a method with nothing to train (KNN) is accepted."""
    model_cls = hydra.utils.get_class(model_cfg._target_)
    if ckpt_path:
        check_checkpoint(read_checkpoint(ckpt_path), model_cls, ckpt_path)
        with safe_loading():
            return model_cls.load_from_checkpoint(ckpt_path, map_location="cpu", weights_only=True)
    model = hydra.utils.instantiate(model_cfg)
    if model.has_trainable_parameters:
        raise ConfigError(
            f"{model_cls.__name__} ({what or f'model={_model_choice()}'}) is a trained model: give its checkpoint "
            "with ckpt_path=<run>/checkpoints/last.ckpt (only a method with nothing to train, model=knn, "
            "runs without one)"
        )
    return model


@task_wrapper
def run(cfg: DictConfig) -> dict:
    started = time.perf_counter()
    positions, had_header = read_query_positions(Path(cfg.positions))
    spec = RunSpec.of(cfg)
    spec.one_scene("graf-synthesize")
    bands, _, neighbors, dm = build_datamodule(spec)
    band = bands[0]
    model = load_model(model_config_for_neighbors(cfg.model, neighbors), cfg.get("ckpt_path"))
    t0 = time.perf_counter()
    spectra = synthesize(model, dm, positions)
    t_pred = time.perf_counter() - t0
    out = Path(cfg.out) if cfg.get("out") else output_dir(cfg) / "synthesized"
    ids = list(range(1, len(positions) + 1))
    write_nerf2_folder(out, spectra, positions, ids, dm.data.gateway_position, dm.data.gateway_orientation)
    result = {
        "method": model.method,
        "scene": dm.data.name,
        "band_hz": band.frequency_hz,
        "n": len(ids),
        "folder": str(out),
        "seconds": round(time.perf_counter() - started, 3),
        "seconds_per_spectrum": round(t_pred / max(len(ids), 1), 4),
        "positions_header": had_header,
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    atomic_write_json(output_dir(cfg) / "results.json", result)
    print(
        f"{len(ids)} spectra synthesized by {result['method']} into {out} ({result['seconds_per_spectrum']:.3f} s each)"
    )
    return result


@torch.no_grad()
def synthesize(model, datamodule, positions: np.ndarray, batch_size: int | None = None) -> torch.Tensor:
    """Spectra ``[N, 90, 360]`` (float32, in [0, 1]) predicted by ``model`` at ``positions`` ``[N, 3]``,
    conditioned on the neighbors from the training split of ``datamodule``'s scene."""
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must be [N, 3], got {positions.shape}")
    if not np.isfinite(positions).all():
        raise ValueError("positions must be finite")
    datamodule.setup("predict")
    model.eval()
    device = next(model.parameters(), torch.zeros(0)).device
    out = []
    for batch in datamodule.query_batches(positions, batch_size):
        batch = {k: v.to(device) for k, v in batch.items()}
        out.append(model.predict_spectra(batch).float().clamp(0, 1).cpu())
    return torch.cat(out) if out else torch.zeros((0, *SPECTRUM_SHAPE))
