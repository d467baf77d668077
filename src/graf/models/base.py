"""Shared LightningModule behaviour of every method: the test protocol and its metrics.

A method implements :meth:`predict_spectra` (batch -> ``[B, 90, 360]``) and, if it learns, ``training_step``
and ``configure_optimizers``.  Test metrics are per-spectrum means over the evaluated split
(``test/mse``, ``test/psnr``, ``test/ssim``, ``test/lpips``); predictions are clamped to [0, 1] first.
"""

from __future__ import annotations

import lightning as L
import torch

from graf.metrics import spectrum_metrics


def adam_exponential_decay(module, lr: float, lr_decay: float, decay_steps: int) -> dict:
    """Adam with the learning rate multiplied by ``lr_decay`` over ``decay_steps`` optimiser steps
    (exponential, stepped every step): the optimiser of GRaF and KNN-DL, in Lightning's return format."""
    opt = torch.optim.Adam(module.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=lr_decay ** (1.0 / max(1, decay_steps)))
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}


class SpectrumModule(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.test_metrics = spectrum_metrics("test/")

    @property
    def has_trainable_parameters(self) -> bool:
        return any(p.requires_grad for p in self.parameters())

    def predict_spectra(self, batch: dict) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def _eval_step(self, batch: dict, metrics) -> dict:
        pred = self.predict_spectra(batch).float().clamp(0.0, 1.0)
        target = batch["tgt_spectrum"].float()
        metrics.update(pred, target)
        self.log_dict(metrics, on_step=False, on_epoch=True, batch_size=pred.shape[0])
        return {"pred": pred.detach(), "ids": batch["tgt_id"].detach()}

    def test_step(self, batch: dict, batch_idx: int) -> dict:
        return self._eval_step(batch, self.test_metrics)
