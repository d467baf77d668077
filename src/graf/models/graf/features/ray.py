"""``model/features=ray``: ray-aligned neighbor features (:mod:`graf.models.graf.features.ray_reading`).

Every spectrum of a scene is measured by the same array, so ray (elevation, azimuth) of the target is pixel
(elevation, azimuth) of every neighbor.  Each neighbor's encoder feature map is projected to
``ray_feature_dim`` channels (a 1 x 1 convolution) once per batch; a ray then reads, per neighbor, that map
at its own pixel, the neighbor's values in a ``(2r+1)^2`` window around it (``pixel_window`` r) and the
neighbor's geometry, and :class:`RayNeighborTokens` turns them into L per-ray tokens that the ray's voxels
cross-attend to.  ``Linear(d, 2)`` turns the ray tracer's state into ``(re, im)``.  The KNN-based modes
(:mod:`.ray_knn`, :mod:`.ray_weights`) extend this one.
"""

from __future__ import annotations

import torch
from torch import nn

from graf.config_home import defaults_from
from graf.models.graf.features.base import Dims, NeighborFeatures, complex_head, neighbor_slots
from graf.models.graf.features.ray_reading import (
    RayNeighborTokens,
    all_pixel_inputs,
    pad_wrap,
    pixel_window,
    rows,
    sample_wrap,
)
from graf.models.graf.inference import split_batch
from graf.models.knn.weights import idw_weights


@defaults_from("model/features/ray.yaml")
class RayFeatures(NeighborFeatures):
    """Args (``conf/model/features/ray.yaml``):
    ray_feature_dim: channels of the projected feature map read per ray.
    pixel_window: radius r of the window of neighbor pixels read per ray (1: 3 x 3; 0: the pixel alone).
    """

    name = "ray"
    method_suffix = "-ray"

    def __init__(
        self,
        dims: Dims,
        residual: bool = False,
        defer_output: bool = False,
        *,
        ray_feature_dim: int,
        pixel_window: int,
    ):
        super().__init__(dims, residual, defer_output)
        if ray_feature_dim < 1 or pixel_window < 0:
            raise ValueError(
                f"model.features.ray_feature_dim must be >= 1 and model.features.pixel_window >= 0, got "
                f"{ray_feature_dim}, {pixel_window}"
            )
        self.pixel_window = int(pixel_window)
        self.ray_proj = nn.Conv2d(dims.encoder_dim, int(ray_feature_dim), 1)
        self.ray_tokens = RayNeighborTokens(
            int(ray_feature_dim), self.pixel_window, dims.offset_dim + 1, dims.mlp_dim, dims.d_model
        )
        if not defer_output:
            self.make_output(dims, residual)

    def make_output(self, dims: Dims, residual: bool) -> None:
        """The output's parameters: ``Linear(d, 2)``, zero at initialisation when the model starts as a KNN
        (with ``model.residual``, or a KNN-based mode's own base)."""
        self.head = complex_head(dims.d_model, zero=residual or self.knn_based)

    def prepare(self, model: nn.Module, batch: dict) -> dict:
        """Each neighbor's projected feature map ``ray_maps [B, L, k, h, w + 2]`` (azimuth-padded, read per ray by
        :func:`sample_wrap`: bilinear at the ray's pixel, never upsampled whole), the spectra ``src [B, L, 90,
        360]`` (padded ones zero) and the geometry's share of the token MLP ``geo [B, L, hidden]``."""
        spectra, mask = batch["src_spectra"].float(), batch["src_mask"].bool()
        encode = lambda x: self.ray_proj(model.encoder.forward_map(x))  # noqa: E731
        ray_maps = neighbor_slots(  # [B, L, k, h, w + 2]
            model,
            mask,
            lambda: pad_wrap(encode(spectra.flatten(0, 1).unsqueeze(1))),
            lambda: pad_wrap(split_batch(encode, spectra[mask].unsqueeze(1))),
        )
        offset, pe_off = model.neighbor_offsets(batch)
        dist_wl = torch.linalg.vector_norm(offset, dim=-1, keepdim=True) / batch["wavelength"].float()[:, None, None]
        ctx = {
            "ray_maps": ray_maps,
            "src": spectra.masked_fill(~mask[..., None, None], 0.0),
            "geo": self.ray_tokens.geometry(torch.cat([pe_off, torch.log1p(dist_wl)], dim=-1)),
        }
        if not (model.training or torch.is_grad_enabled()):  # inference renders every pixel once: read all at once
            ctx["ray_inputs"] = all_pixel_inputs(ray_maps, ctx["src"], self.pixel_window)
        return ctx

    def scene_inputs(self, ctx: dict, q: torch.Tensor, bi: torch.Tensor, pix: torch.Tensor, one_item: bool):
        """Each ray's voxels attend to that ray's own L neighbor tokens; the per-ray state holds the window of
        neighbor values ``window [n, L, K]``, the tokens ``[n, L, d]`` and their weight logits ``[n, L]``."""
        if "ray_inputs" in ctx:  # inference: every pixel's inputs read at once (prepare)
            inputs = ctx["ray_inputs"][bi, pix]  # [n, L, k + K]
            window = inputs[..., ctx["ray_maps"].shape[2] :]
            tokens, logits = self.ray_tokens.from_inputs(inputs, rows(ctx["geo"], bi))
        else:
            window = pixel_window(ctx["src"], bi, pix, self.pixel_window)  # [n, L, K]
            feats = sample_wrap(ctx["ray_maps"], bi, pix, ctx["ray_maps"].shape[-1] - 2)  # [n, L, k]
            tokens, logits = self.ray_tokens(feats, window, rows(ctx["geo"], bi))
        key_mask = None if ctx["key_mask"] is None else ctx["key_mask"][bi]
        return q, tokens, key_mask, {"window": window, "tokens": tokens, "logits": logits}

    def output(self, state: torch.Tensor, ray: dict) -> torch.Tensor:
        return self.head(state).float()


def centre_values(window: torch.Tensor) -> torch.Tensor:
    """The neighbors' values at the ray's own pixel ``[n, L]``: the centre of their windows ``[n, L, K]``."""
    return window[..., window.shape[-1] // 2]


def idw_logits(batch: dict) -> torch.Tensor:
    """IDW's log-weights ``[B, L]`` (-inf for padded neighbors): the KNN-based modes' weights at step 0."""
    mask = batch["src_mask"].bool()
    return torch.log(idw_weights(batch["tgt_pos"], batch["src_pos"], mask).float()).masked_fill(~mask, float("-inf"))
