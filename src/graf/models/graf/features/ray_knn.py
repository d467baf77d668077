"""``model/features=ray_knn``: as ``ray``, plus per ray a convex combination of the neighbors' values at the
ray's pixel, its weights ``softmax(IDW log-weights + the tokens' weight logits)`` (IDW KNN at step 0: the
logits' head starts at zero), added to the real part of the ray tracer's ``(re, im)``, whose head also
starts at zero: at initialisation the model *is* per-ray IDW KNN, then the ray tracer corrects it."""

from __future__ import annotations

import torch
from torch import nn

from graf.models.graf.features.ray import RayFeatures, centre_values, idw_logits


class RayKNNFeatures(RayFeatures):
    """:class:`RayFeatures` plus a per-ray base: a convex combination of the neighbors' pixel values (IDW KNN at
    step 0, its weights then learned), which the ray tracer corrects; method ``graf-ray-knn``."""

    name = "ray_knn"
    method_suffix = "-ray-knn"
    knn_based = True

    def prepare(self, model: nn.Module, batch: dict) -> dict:
        return {**super().prepare(model, batch), "idw_logits": idw_logits(batch)}

    def scene_inputs(self, ctx: dict, q: torch.Tensor, bi: torch.Tensor, pix: torch.Tensor, one_item: bool):
        x, tokens, key_mask, ray = super().scene_inputs(ctx, q, bi, pix, one_item)
        w = torch.softmax(ctx["idw_logits"][bi] + ray["logits"], dim=-1)  # convex weights: IDW at init, then learned
        return x, tokens, key_mask, {**ray, "base": (w * centre_values(ray["window"])).sum(dim=-1)}  # base [n]

    def output(self, state: torch.Tensor, ray: dict) -> torch.Tensor:
        out = self.head(state).float()  # the ray tracer corrects the per-ray KNN value: (re + base, im)
        return torch.stack([out[:, 0] + ray["base"].float(), out[:, 1]], dim=-1)
