"""Spectrum synthesis for users: predict spectra at new transmitter positions (the paper's use: more
spectra for training localization models).

    from graf.synthesize import synthesize
    spectra = synthesize(model, datamodule, positions)        # [N, 90, 360] in [0, 1]

``graf-synthesize`` does the same from a checkpoint and writes a NeRF2-format folder.
"""

from __future__ import annotations

import numpy as np
import torch

from graf.geometry.grid import SPECTRUM_SHAPE


@torch.no_grad()
def synthesize(model, datamodule, positions: np.ndarray, batch_size: int | None = None) -> torch.Tensor:
    """Spectra ``[N, 90, 360]`` (float32, in [0, 1]) predicted by ``model`` at ``positions`` ``[N, 3]``,
    conditioned on the neighbours from the training split of ``datamodule``'s scene."""
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
