"""``model/features=pooled`` (the paper's, section 3 / appendix D): one token per neighbor spectrum,
``MLP1(ResNet18(SS_l) ⊕ PE(P_l) ⊕ PE(P_l - P))`` -> ``d_model``, computed once per batch (never per ray);
padded neighbors are masked out.  Every voxel of every ray attends to its target's L tokens, and
``Linear(d, 2)`` turns the ray tracer's state into ``(re, im)``."""

from __future__ import annotations

import torch
from torch import nn

from graf.models.graf.features.base import Dims, NeighborFeatures, complex_head, mlp, neighbor_slots
from graf.models.graf.features.ray_reading import rows


class PooledFeatures(NeighborFeatures):
    """The paper's neighbor features (supplement D): one token per neighbor spectrum, its pooled encoder features
    with the neighbor's position and offset to the voxel (MLP1), read by every voxel's cross-attention; method
    ``graf``."""

    name = "pooled"
    method_suffix = ""

    def __init__(self, dims: Dims, residual: bool = False, defer_output: bool = False):
        super().__init__(dims, residual, defer_output)
        self.mlp1 = mlp(dims.encoder_dim + dims.position_dim + dims.offset_dim, dims.mlp_dim, dims.d_model)
        if not defer_output:
            self.make_output(dims, residual)

    def make_output(self, dims: Dims, residual: bool) -> None:
        """``Linear(d, 2)``, zero at initialisation with ``model.residual`` (the model starts as KNN)."""
        self.head = complex_head(dims.d_model, zero=residual)

    def prepare(self, model: nn.Module, batch: dict) -> dict:
        """``tokens [B, L, d]`` (zero for padded neighbors); the encoder sees only the real neighbors' spectra
        (once per distinct spectrum at evaluation: :meth:`GRaFModule.spectrum_features`)."""
        spectra, mask = batch["src_spectra"], batch["src_mask"].bool()
        feats = neighbor_slots(
            model,
            mask,
            lambda: model.encoder(spectra.flatten(0, 1).unsqueeze(1).float()),
            lambda: model.spectrum_features(spectra[mask]),  # [N_real, C]
        )
        pe_pos = model.pe(model.coords(batch["src_pos"].float(), batch))
        _, pe_off = model.neighbor_offsets(batch)
        tokens = self.mlp1(torch.cat([feats.float(), pe_pos, pe_off], dim=-1))
        return {"tokens": torch.where(mask[..., None], tokens, torch.zeros_like(tokens))}

    def scene_inputs(self, ctx: dict, q: torch.Tensor, bi: torch.Tensor, pix: torch.Tensor, one_item: bool):
        key_mask = ctx["key_mask"]
        if one_item:  # every voxel of the group attends to the same target's neighbors: one long query axis
            b = int(bi[0])
            x = q.reshape(1, q.shape[0] * q.shape[1], q.shape[2])
            return x, ctx["tokens"][b : b + 1], None if key_mask is None else key_mask[b : b + 1], {}
        # each ray's voxels attend to its own target's neighbors
        return q, rows(ctx["tokens"], bi), None if key_mask is None else key_mask[bi], {}

    def output(self, state: torch.Tensor, ray: dict) -> torch.Tensor:
        return self.head(state).float()
