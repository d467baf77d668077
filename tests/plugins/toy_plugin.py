"""A plugin of the worked examples (docs/extending.md): a metric, a study axis and two methods, each added in one
place through graf's interface and nothing else.  Loaded by ``GRAF_PLUGINS=toy_plugin`` (this folder on
``PYTHONPATH``), or by an entry point of the group ``graf.plugins`` when installed (``pyproject.toml`` beside it);
the methods' configs are in ``tests/plugins/conf/model/``, registered once below (``add_conf``)."""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from graf.metrics.names import Metric
from graf.metrics.names import register as register_metric
from graf.models.base import SpectrumModule, adam_exponential_decay
from graf.plugins import add_conf
from graf.reports.axes import Axis
from graf.reports.axes import register as register_axis

add_conf(Path(__file__).parent / "conf")  # model=neighbor_mean and model=neighbor_gain in every graf command


# --- a metric: the angle between the strongest pixel of the prediction and of the measurement (the direction of
# the strongest path), one entry
def peak_error_deg(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``[N, 90, 360] x [N, 90, 360] -> [N]``: the great-circle angle (degrees) between the two spectra's peaks;
    row r is elevation r + 0.5 degrees, column c azimuth c + 0.5 degrees."""

    def direction(x: torch.Tensor) -> torch.Tensor:
        flat = x.flatten(1).argmax(dim=1)
        el = torch.deg2rad((flat // x.shape[-1]).double() + 0.5)
        az = torch.deg2rad((flat % x.shape[-1]).double() + 0.5)
        return torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], dim=-1)

    cos = (direction(pred) * direction(target)).sum(dim=-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cos))


register_metric(Metric("peak_error", "peak error", "deg", False, "{:.1f}", per_spectrum=peak_error_deg))


# --- a study axis: the neighbour search radius (wavelengths), one entry
register_axis(Axis("radius", of_job=lambda r: ((r.get("config") or {}).get("neighbors") or {}).get("radius")))


# --- a method: the plain mean of the neighbors' spectra (nothing to train), the Method interface
class NeighborMeanModule(SpectrumModule):
    """The unweighted mean of the L neighbors' spectra (method ``neighbor-mean``): KNN without its weights."""

    def predict_spectra(self, batch: dict) -> torch.Tensor:
        mask = batch["src_mask"].to(batch["src_spectra"].dtype)  # [B, L]: padded neighbors out
        w = mask / mask.sum(dim=1, keepdim=True).clamp_min(1.0)
        return torch.einsum("bl,blhw->bhw", w, batch["src_spectra"])


# --- a method that trains: the neighbors' mean times a learned gain (one parameter), trained on the MSE
class NeighborGainModule(SpectrumModule):
    """The mean of the L neighbors' spectra times ``exp(log_gain)``, clamped to [0, 1] (method ``neighbor-gain``):
    the smallest method with something to train, checkpoint and read back."""

    def __init__(self, lr: float = 0.05, lr_decay: float = 1.0, decay_steps: int | None = None):
        super().__init__()
        self.save_hyperparameters()
        self.lr, self.lr_decay, self.decay_steps = float(lr), float(lr_decay), decay_steps
        self.log_gain = nn.Parameter(torch.zeros(()))

    def predict_spectra(self, batch: dict) -> torch.Tensor:
        mask = batch["src_mask"].to(batch["src_spectra"].dtype)
        w = mask / mask.sum(dim=1, keepdim=True).clamp_min(1.0)
        mean = torch.einsum("bl,blhw->bhw", w, batch["src_spectra"].float())
        return (mean * self.log_gain.exp()).clamp(0.0, 1.0)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        loss = F.mse_loss(self.predict_spectra(batch), batch["tgt_spectrum"].float())
        self.log("train/loss", loss, batch_size=batch["tgt_pos"].shape[0])
        return loss

    def configure_optimizers(self):
        return adam_exponential_decay(self, self.lr, self.lr_decay, self.decay_steps)
