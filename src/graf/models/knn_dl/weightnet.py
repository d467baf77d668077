"""KNN-DL's weight network: low-resolution per-neighbor fusion maps from the geometry alone.

For each (target, neighbor) pair the network sees only relative geometry, never a spectrum:

- ``PE(normalize_offsets(P_l - P_t))`` (``pe_freqs`` bands: 3 -> 3 (1 + 2F) dims),
- ``log(1 + d_l / wavelength)``, the neighbor's distance rank among the target's real neighbors
  (``rank / max_rank``) and the number of real neighbors (``n / max_rank``).

A per-neighbor MLP embeds these, one DeepSets layer adds the masked mean over the target's real
neighbors (so a neighbor's weight can depend on where the *other* neighbors lie, e.g. whether the
target is inside their hull), and the result is decoded on a coarse ``map_size`` grid of ray
directions: every cell contributes ``PE(its gateway-frame ray direction)`` (``dir_freqs`` bands) and the
cosine between that ray (in the world frame) and the neighbor's offset direction.  The decoder's first
layer is a sum of the per-neighbor, per-cell and cosine terms (each computed once), then ReLU ->
Linear -> ReLU -> Linear to two channels per cell: a fusion logit and a signed correction.  The last
layer is zero-initialised, so both maps are 0 at initialisation.

:func:`upsample_maps` brings the coarse maps to the 90 x 360 spectrum grid bilinearly, circular in
azimuth (azimuth 360 deg neighbors 1 deg) and edge-clamped in elevation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from graf.geometry.encoding import PositionalEncoding
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION, directions

CHANNELS = 2  # fusion logit, signed correction


def cell_directions(map_size: Sequence[int]) -> torch.Tensor:
    """``[h * w, 3]`` gateway-frame unit directions of the centres of a coarse ``h x w`` grid over the
    spectrum (row-major, azimuth fastest); cell centres are where :func:`upsample_maps` puts them."""
    h, w = map_size
    # pixel r is elevation r + 1 deg, pixel c azimuth c + 1 deg (graf.geometry.grid.grid_directions)
    el = (torch.arange(h, dtype=torch.float64) + 0.5) * (N_ELEVATION / h) - 0.5 + 1.0
    az = (torch.arange(w, dtype=torch.float64) + 0.5) * (N_AZIMUTH / w) - 0.5 + 1.0
    return directions(el, az).float()


def upsample_maps(maps: torch.Tensor) -> torch.Tensor:
    """``[..., h, w]`` coarse maps -> ``[..., 90, 360]``, bilinear, circular in azimuth.

    One coarse column is wrapped onto each side before interpolating and the margin cut afterwards, so
    cell centres land at pixel ``(i + 0.5) * 360 / w - 0.5`` and the first and last columns blend."""
    lead, (h, w) = maps.shape[:-2], maps.shape[-2:]
    sx = N_AZIMUTH // w
    x = maps.reshape(-1, 1, h, w)
    x = torch.cat([x[..., -1:], x, x[..., :1]], dim=-1)
    x = F.interpolate(x, size=(N_ELEVATION, N_AZIMUTH + 2 * sx), mode="bilinear", align_corners=False)
    return x[..., sx : sx + N_AZIMUTH].reshape(*lead, N_ELEVATION, N_AZIMUTH)


class WeightNet(nn.Module):
    """Geometry -> coarse fusion maps ``[B, L, 2, h, w]`` (channel 0: logit, 1: signed correction).

    Args:
        map_size: coarse grid (h, w); h must divide 90 and w divide 360.
        hidden: width of the per-neighbor MLP and the DeepSets layer.
        decoder_hidden: width of the per-cell decoder.
        pe_freqs: frequency bands of the offset's positional encoding.
        dir_freqs: frequency bands of the ray direction's positional encoding.
        max_rank: scale of the rank and neighbor-count features (the largest L expected).

    Built by :class:`KNNDLModule` from its settings (their defaults: ``conf/model/knn_dl.yaml``).
    """

    def __init__(
        self,
        map_size: Sequence[int],
        hidden: int,
        decoder_hidden: int,
        pe_freqs: int,
        dir_freqs: int,
        max_rank: int,
    ):
        super().__init__()
        self.map_size = (int(map_size[0]), int(map_size[1]))
        self.max_rank = float(max_rank)
        self.pe_offset = PositionalEncoding(pe_freqs)
        self.pe_dir = PositionalEncoding(dir_freqs)
        d_in = self.pe_offset.out_dim(3) + 3
        self.embed = nn.Linear(d_in, hidden)
        self.set_self = nn.Linear(hidden, hidden)
        self.set_ctx = nn.Linear(hidden, hidden, bias=False)
        self.to_decoder = nn.Linear(hidden, decoder_hidden)
        self.cell = nn.Linear(self.pe_dir.out_dim(3), decoder_hidden, bias=False)
        self.cosine = nn.Parameter(torch.zeros(decoder_hidden))
        nn.init.normal_(self.cosine, std=1.0 / math.sqrt(decoder_hidden))
        self.decoder = nn.Sequential(
            nn.ReLU(), nn.Linear(decoder_hidden, decoder_hidden), nn.ReLU(), nn.Linear(decoder_hidden, CHANNELS)
        )
        nn.init.zeros_(self.decoder[-1].weight)
        nn.init.zeros_(self.decoder[-1].bias)
        self.register_buffer("cell_dirs", cell_directions(self.map_size), persistent=False)

    def neighbor_features(self, offset_norm: torch.Tensor, dist_wl: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``[B, L, d_in]``: PE of the normalised offset, log(1 + d / wavelength), rank, neighbor count."""
        rank = torch.where(mask, dist_wl, torch.full_like(dist_wl, float("inf"))).argsort(dim=1, stable=True)
        rank = rank.argsort(dim=1).to(dist_wl.dtype)  # 0 for the nearest real neighbor
        count = mask.sum(dim=1, keepdim=True).to(dist_wl.dtype).expand_as(dist_wl)
        scalars = torch.stack([torch.log1p(dist_wl), rank / self.max_rank, count / self.max_rank], dim=-1)
        return torch.cat([self.pe_offset(offset_norm), scalars], dim=-1)

    def forward(
        self,
        offset_norm: torch.Tensor,
        offset_world: torch.Tensor,
        wavelength: torch.Tensor,
        mask: torch.Tensor,
        gw_rot: torch.Tensor,
    ) -> torch.Tensor:
        """Args: normalised offsets ``[B, L, 3]``, world offsets (m) ``[B, L, 3]``, wavelength (m) ``[B]``,
        mask ``[B, L]`` bool, gateway rotation (local -> world) ``[B, 3, 3]``."""
        B, L = mask.shape
        dist = torch.linalg.vector_norm(offset_world, dim=-1)  # [B, L]
        g = self.neighbor_features(offset_norm, dist / wavelength[:, None], mask)
        h = F.relu(self.embed(g))
        m = mask[..., None].to(h.dtype)
        ctx = (h * m).sum(dim=1, keepdim=True) / m.sum(dim=1, keepdim=True).clamp_min(1.0)
        z = F.relu(self.set_self(h) + self.set_ctx(ctx))
        per_nbr = self.to_decoder(z)  # [B, L, H]
        per_cell = self.cell(self.pe_dir(self.cell_dirs))  # [C, H]
        dirs = torch.einsum("bij,cj->bci", gw_rot, self.cell_dirs)  # world ray directions [B, C, 3]
        unit = offset_world / dist[..., None].clamp_min(1e-9)  # zero vector for a co-located neighbor
        cos = torch.einsum("bli,bci->blc", unit, dirs)  # [B, L, C]
        x = per_nbr[:, :, None, :] + per_cell[None, None] + cos[..., None] * self.cosine
        out = self.decoder(x)  # [B, L, C, 2]
        return out.permute(0, 1, 3, 2).reshape(B, L, CHANNELS, *self.map_size)
