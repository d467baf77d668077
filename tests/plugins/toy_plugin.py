"""A plugin of the worked examples (docs/extending.md): a metric, a study axis and a method, each added in one
place through graf's interface and nothing else.  Loaded by ``GRAF_PLUGINS=toy_plugin`` (this folder on
``PYTHONPATH``); the method's config is ``tests/plugins/conf/model/neighbor_mean.yaml``
(``hydra.searchpath=[file://tests/plugins/conf]``)."""

from __future__ import annotations

import torch

from graf.metrics.names import Metric
from graf.metrics.names import register as register_metric
from graf.models.base import SpectrumModule
from graf.reports.axes import Axis
from graf.reports.axes import register as register_axis


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


# --- a study axis: how sparse the neighbors are (no known transmitter within this many wavelengths), one entry
register_axis(
    Axis("exclude_within", of_job=lambda r: ((r.get("config") or {}).get("neighbors") or {}).get("exclude_within"))
)


# --- a method: the plain mean of the neighbors' spectra (nothing to train), the Method interface
class NeighborMeanModule(SpectrumModule):
    """The unweighted mean of the L neighbors' spectra (method ``neighbor-mean``): KNN without its weights."""

    def predict_spectra(self, batch: dict) -> torch.Tensor:
        mask = batch["src_mask"].to(batch["src_spectra"].dtype)  # [B, L]: padded neighbors out
        w = mask / mask.sum(dim=1, keepdim=True).clamp_min(1.0)
        return torch.einsum("bl,blhw->bhw", w, batch["src_spectra"])
