"""A training run stopped at a checkpoint and resumed draws exactly the batches (targets, L, neighbors) of an
uninterrupted run and ends with the same weights, mid-epoch and across epoch boundaries (Lightning's own loop)."""

from __future__ import annotations

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from torch import nn

from graf.bands import Band
from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector
from graf.data.scenes import NeRF2Scene
from graf.models.base import SpectrumModule


class Recorder(SpectrumModule):
    """Records every training batch; its one weight follows the batches, so the final weight depends on them."""

    def __init__(self):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(3))
        self.seen: dict[int, tuple] = {}

    def training_step(self, batch, batch_idx):
        self.seen[int(self.global_step)] = (
            batch["tgt_index"].clone(),
            batch["src_index"].clone(),
            batch["src_mask"].clone(),
        )
        x = batch["src_pos"][batch["src_mask"]].mean(0) + batch["src_mask"].float().mean()
        return ((self.w - x) ** 2).sum()

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=0.05)

    def predict_spectra(self, batch):  # pragma: no cover - not evaluated here
        raise NotImplementedError


def _dm(num_workers=0):
    return SpectrumDataModule(
        NeRF2Scene("rfid_s23", "embedded:rfid_s23_200"),
        Band("915mhz", 915e6),
        NeighborSelector(L=10, L_train=(3, 10), radius=10.0),
        batch_size=8,
        num_workers=num_workers,
    )


def _fit(max_steps, root, ckpt_path=None, num_workers=0):
    model = Recorder()
    trainer = L.Trainer(
        max_steps=max_steps,
        max_epochs=-1,
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
        callbacks=[ModelCheckpoint(dirpath=root, save_last=True, every_n_train_steps=5)],
    )
    trainer.fit(model, datamodule=_dm(num_workers), ckpt_path=ckpt_path)
    return model


@pytest.mark.parametrize("stop_at", [10, 20, 35])  # mid-epoch 0, mid-epoch 1, just before the end of epoch 1
def test_resumed_run_draws_the_same_batches_and_ends_with_the_same_weights(tmp_path, stop_at):
    torch.manual_seed(0)
    full = _fit(40, tmp_path / "full")
    torch.manual_seed(0)
    _fit(stop_at, tmp_path / "part")
    resumed = _fit(40, tmp_path / "resumed", ckpt_path=tmp_path / "part" / "last.ckpt")
    assert sorted(resumed.seen) == list(range(stop_at, 40))  # no batch repeated or skipped
    for step, (tgt, src, mask) in resumed.seen.items():
        ftgt, fsrc, fmask = full.seen[step]
        assert torch.equal(tgt, ftgt) and torch.equal(src, fsrc) and torch.equal(mask, fmask), step
    assert torch.equal(resumed.w.detach(), full.w.detach())
    # the draws really vary from batch to batch (this is not a constant stream)
    assert len({tuple(m.sum(1).tolist()) for _, _, m in full.seen.values()}) > 20


def test_loader_workers_give_the_uninterrupted_stream(tmp_path):
    a = _fit(12, tmp_path / "a", num_workers=0)
    b = _fit(12, tmp_path / "b", num_workers=2)
    assert all(torch.equal(a.seen[k][1], b.seen[k][1]) for k in range(12))
