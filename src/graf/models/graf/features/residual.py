"""``model.residual``: GRaF as a correction of KNN.  With ``residual=true`` the KNN interpolation
``base = sum_l w_l SS_l(ray)`` (``weighting`` ``idw`` or ``barycentric``, :mod:`graf.models.knn.weights`) is
added to the real part of every ray's ``(re, im)``; the component's output head starts at zero, so at
initialisation the model *is* KNN.  :class:`NoBase` is the plain model (nothing added)."""

from __future__ import annotations

import torch
from torch import nn

from graf.geometry.rays import fp32
from graf.models.knn.weights import barycentric_weights, idw_weights

WEIGHTINGS = ("idw", "barycentric")


def knn_weights(batch: dict, weighting: str) -> torch.Tensor:
    """``[B, L]`` convex weights of the KNN base (as :class:`graf.models.knn.KNNModule`)."""
    args = (batch["tgt_pos"], batch["src_pos"], batch["src_mask"])
    return idw_weights(*args) if weighting == "idw" else barycentric_weights(*args)


class KNNBase(nn.Module):
    """Adds the KNN base of ``weighting`` to the real part of the predicted rays."""

    def __init__(self, weighting: str):
        super().__init__()
        self.weighting = weighting

    def prepare(self, batch: dict, mask: torch.Tensor) -> dict:
        """The batch's KNN weights ``base_w [B, L]`` and flat neighbor spectra ``base_src [B, L, P]``."""
        src = batch["src_spectra"].flatten(2).float().masked_fill(~mask[..., None], 0.0)
        return {"base_w": knn_weights(batch, self.weighting).float(), "base_src": src}

    def add(self, ctx: dict, pix: torch.Tensor, re: torch.Tensor) -> torch.Tensor:
        """``re [B, R]`` of the pixels ``pix [B, R]`` plus the KNN base there."""
        with fp32(pix.device):
            src = ctx["base_src"].gather(2, pix[:, None, :].expand(-1, ctx["base_src"].shape[1], -1))
            return re + torch.einsum("bl,blr->br", ctx["base_w"], src)


class NoBase(nn.Module):
    """``residual=false``: nothing is added."""

    def prepare(self, batch: dict, mask: torch.Tensor) -> dict:
        return {}

    def add(self, ctx: dict, pix: torch.Tensor, re: torch.Tensor) -> torch.Tensor:
        return re
