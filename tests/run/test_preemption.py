"""The pre-emption callback saves a resumable checkpoint wherever Lightning stops at a SIGTERM: after a training
step, and also after a validation batch (a signal that lands in a validation pass)."""

from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from lightning.pytorch.utilities.exceptions import SIGTERMException
from torch.utils.data import DataLoader, TensorDataset

from graf.callbacks import Preemption


class Tiny(pl.LightningModule):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        return self.lin(batch[0]).pow(2).mean()

    def validation_step(self, batch, batch_idx):
        self.log("val_out", self.lin(batch[0]).mean())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


class SignalIn(pl.Callback):
    """Raises Lightning's SIGTERM flag as a real signal would: in the validation pass after ``step``, or in step
    ``step``'s training batch."""

    def __init__(self, step: int, where: str):
        self.step, self.where = step, where

    def _flag(self, trainer):
        if trainer.global_step == self.step and not trainer.sanity_checking:
            trainer._signal_connector.received_sigterm = True

    def on_validation_batch_start(self, trainer, *args):
        if self.where == "validation":
            self._flag(trainer)

    def on_train_batch_start(self, trainer, *args):
        if self.where == "training":
            self._flag(trainer)


def _fit(tmp_path, callbacks, ckpt_path=None) -> pl.Trainer:
    torch.manual_seed(0)
    data = TensorDataset(torch.randn(64, 2))
    trainer = pl.Trainer(
        max_steps=20,
        val_check_interval=5,
        num_sanity_val_steps=0,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=callbacks,
        default_root_dir=tmp_path,
    )
    trainer.fit(Tiny(), DataLoader(data, batch_size=4), DataLoader(data[:12], batch_size=4), ckpt_path=ckpt_path)
    return trainer


@pytest.mark.parametrize("where, saved_step", [("validation", 10), ("training", 8)])
def test_a_sigterm_saves_a_checkpoint_that_resumes_to_the_end(tmp_path, where, saved_step):
    pre = Preemption(tmp_path / "ckpt")
    with pytest.raises(SIGTERMException):
        _fit(tmp_path, [pre, SignalIn(10 if where == "validation" else 8, where)])
    assert pre.saved is not None, f"a SIGTERM in {where} left no checkpoint"
    assert pre.saved["global_step"] == saved_step + (where == "training")  # a training step finishes first
    state = torch.load(pre.saved["checkpoint"], map_location="cpu", weights_only=False)
    assert state["global_step"] == pre.saved["global_step"]
    resumed = _fit(tmp_path, [], ckpt_path=pre.saved["checkpoint"])
    assert resumed.global_step == 20
