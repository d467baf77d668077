"""``model/features=ray_weights`` (the main job's, ``graf-ray-weights``): as ``ray_knn``, but the output is
*only* the per-ray convex combination of the neighbors' values at the ray's pixel, never an additive term, so
every predicted pixel is a weighted average of what the neighbors measured there.  Its weights are
``softmax(IDW log-weights + the tokens' weight logits + scores)``: the ray tracer's state, through
``weight_query`` (zero at initialisation: IDW KNN at step 0), scores the ray's L neighbor tokens."""

from __future__ import annotations

import math

import torch
from torch import nn

from graf.models.graf.features.base import Dims
from graf.models.graf.features.ray import RayFeatures, centre_values, idw_logits


class RayWeightsFeatures(RayFeatures):
    """Only the per-ray convex combination of the neighbors' pixel values (IDW KNN at step 0), its weights
    corrected by the per-ray tokens and the ray tracer's state: it re-weights what the neighbors measured and
    cannot predict a value none of them measured; method ``graf-ray-weights``."""

    name = "ray_weights"
    method_suffix = "-ray-weights"
    knn_based = True

    def make_output(self, dims: Dims, residual: bool) -> None:
        """``weight_query``: the ray tracer's state -> a query over the L per-ray tokens (zero at init)."""
        self.weight_query = nn.Linear(dims.d_model, dims.d_model)
        nn.init.zeros_(self.weight_query.weight)
        nn.init.zeros_(self.weight_query.bias)

    def prepare(self, model: nn.Module, batch: dict) -> dict:
        return {**super().prepare(model, batch), "idw_logits": idw_logits(batch)}

    def scene_inputs(self, ctx: dict, q: torch.Tensor, bi: torch.Tensor, pix: torch.Tensor, one_item: bool):
        x, tokens, key_mask, ray = super().scene_inputs(ctx, q, bi, pix, one_item)
        return x, tokens, key_mask, {**ray, "logits": ctx["idw_logits"][bi] + ray["logits"]}

    def output(self, state: torch.Tensor, ray: dict) -> torch.Tensor:
        """``(value, 0)``: the convex combination, its weights corrected by the state's scores of the tokens."""
        query = self.weight_query(state)
        scores = (query[:, None, :] * ray["tokens"].float()).sum(dim=-1) / math.sqrt(self.dims.d_model)  # [n, L]
        w = torch.softmax(ray["logits"].float() + scores, dim=-1)
        value = (w * centre_values(ray["window"]).float()).sum(dim=-1)  # [n]
        return torch.stack([value, torch.zeros_like(value)], dim=-1)
