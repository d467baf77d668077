"""Callbacks that turn a test run into files: predictions and the predicted-vs-true figure."""

from __future__ import annotations

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback

from graf.geometry.grid import SPECTRUM_SHAPE


class PredictionCollector(Callback):
    """Keeps the test predictions, targets and ids (float32 on CPU) for results files and figures."""

    def __init__(self):
        self.pred: list[torch.Tensor] = []
        self.target: list[torch.Tensor] = []
        self.ids: list[torch.Tensor] = []

    def on_test_epoch_start(self, trainer, pl_module) -> None:
        self.pred, self.target, self.ids = [], [], []

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self.pred.append(outputs["pred"].detach().float().cpu())
        self.target.append(batch["tgt_spectrum"].detach().float().cpu())
        self.ids.append(batch["tgt_id"].detach().cpu())

    def arrays(self) -> dict[str, np.ndarray]:
        if not self.pred:
            return {"pred": np.zeros((0, *SPECTRUM_SHAPE), np.float32), "target": np.zeros((0, *SPECTRUM_SHAPE), np.float32),
                    "ids": np.zeros((0,), np.int64)}
        return {"pred": torch.cat(self.pred).numpy().astype(np.float32),
                "target": torch.cat(self.target).numpy().astype(np.float32),
                "ids": torch.cat(self.ids).numpy().astype(np.int64)}
