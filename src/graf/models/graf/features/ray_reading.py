"""Ray-aligned neighbor features (``model/features=ray``, ``ray_knn`` and ``ray_weights``).

Every spectrum of a scene is measured by the same array, so ray (elevation, azimuth) of the target is pixel
(elevation, azimuth) of every neighbor.  Instead of pooling each neighbor's spectrum to one vector, a ray
reads, for each neighbor l:

- the neighbor's encoder feature map (projected to ``k`` channels) at the ray's direction, bilinear at the
  pixel centre, the azimuth wrapping at 360 degrees and the elevation clamped at its ends
  (:func:`upsample_wrap`),
- the neighbor's own values in a ``(2r+1) x (2r+1)`` window around that pixel (:func:`pixel_window`; the
  centre is its value at the pixel),
- the neighbor's geometry: its offset from the target in the gateway frame (PE) and its distance in
  wavelengths (``log1p``).

:class:`RayNeighborTokens` turns these into L per-ray tokens ``[n, L, d]`` (a two-layer MLP whose geometry
part is computed once per batch), which the voxel queries of that ray cross-attend to.  Its ``weight_logits``
head (zero at initialisation) corrects IDW's logits per ray: the ``ray_knn`` variant's convex weights.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from graf.geometry.grid import N_AZIMUTH, N_ELEVATION


def upsample_wrap(maps: torch.Tensor) -> torch.Tensor:
    """``[N, k, h, w]`` maps over the whole 90 x 360 grid -> ``[N, k, 90, 360]``: each spectrum pixel's value
    bilinear at its centre, with the azimuth periodic (the last map column is the first one's neighbor) and
    the elevation clamped (no wrap).  A map already at 90 x 360 comes back unchanged."""
    h, w = maps.shape[-2:]
    padded = pad_wrap(maps)  # [N, k, h, w + 2]: one wrapped column each side
    y0, y1, wy, x0, x1, wx = _centre_coords(h, w, maps.device)
    wy, wx = wy.to(maps.dtype)[:, None], wx.to(maps.dtype)
    rows = padded[:, :, y0] * (1 - wy) + padded[:, :, y1] * wy  # [N, k, 90, w + 2]
    return rows[..., x0] * (1 - wx) + rows[..., x1] * wx


def _centre_coords(h: int, w: int, device) -> tuple:
    """Bilinear corners and weights of every elevation row (in a map of ``h`` rows, clamped) and azimuth
    column (in a map of ``w`` columns padded by one wrapped column each side) at the pixel centres."""
    y = ((torch.arange(N_ELEVATION, device=device, dtype=torch.float32) + 0.5) * (h / N_ELEVATION) - 0.5).clamp(
        0, h - 1
    )
    x = (torch.arange(N_AZIMUTH, device=device, dtype=torch.float32) + 0.5) * (w / N_AZIMUTH) - 0.5 + 1.0
    y0 = y.floor().long().clamp(0, h - 1)
    x0 = x.floor().long()
    return y0, (y0 + 1).clamp(max=h - 1), y - y0.float(), x0, (x0 + 1).clamp(max=w + 1), x - x0.float()


def rows(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[index]`` along the first axis by ``index_select``: the same values, and a backward that adds the
    gradients of repeated rows in a fixed order.  Advanced indexing's backward (``index_put_`` with accumulate)
    adds them with atomics across CPU threads, so a 2-thread training varied in its last bits from run to run
    (issue 52)."""
    return x.index_select(0, index.reshape(-1)).view(*index.shape, *x.shape[1:])


def pad_wrap(maps: torch.Tensor) -> torch.Tensor:
    """``[..., h, w]`` -> ``[..., h, w + 2]``: one wrapped azimuth column on each side."""
    return torch.cat([maps[..., -1:], maps, maps[..., :1]], dim=-1)


def sample_wrap(padded: torch.Tensor, bi: torch.Tensor, pix: torch.Tensor, w: int) -> torch.Tensor:
    """``upsample_wrap`` read at the given pixels only: ``padded [B, L, k, h, w + 2]`` (:func:`pad_wrap` of the
    maps), items ``bi [n]``, pixels ``pix [n]`` -> ``[n, L, k]``, the same values (the same arithmetic in the
    same order) as ``upsample_wrap(maps)[b, l, :, row, col]``, at a cost linear in the rays drawn."""
    _, L, k, h, w2 = padded.shape
    y0, y1, wy, x0, x1, wx = _centre_coords(h, w, padded.device)
    r, c = pix // N_AZIMUTH, pix % N_AZIMUTH
    wy, wx = wy.to(padded.dtype)[r][:, None, None], wx.to(padded.dtype)[c][:, None, None]
    flat = padded.reshape(-1)  # read by index_select: a backward that adds in a fixed order (see rows)
    channel = (torch.arange(L * k, device=padded.device) * (h * w2)).view(1, L, k)  # [1, L, k]
    item = (bi * (L * k * h * w2)).view(-1, 1, 1)

    def at(ys, xs):  # [n, L, k]
        return rows(flat, item + channel + (ys * w2 + xs).view(-1, 1, 1))

    top = at(y0[r], x0[c]) * (1 - wy) + at(y1[r], x0[c]) * wy
    bottom = at(y0[r], x1[c]) * (1 - wy) + at(y1[r], x1[c]) * wy
    return top * (1 - wx) + bottom * wx


def pixel_window(spectra: torch.Tensor, bi: torch.Tensor, pix: torch.Tensor, radius: int) -> torch.Tensor:
    """Values ``[n, L, (2r+1)^2]`` of every neighbor spectrum (``spectra [B, L, 90, 360]``) in the window of
    radius ``r`` around pixel ``pix [n]`` (``row * 360 + col``) of item ``bi [n]``; the azimuth wraps, the
    elevation is clamped.  The window's centre (index ``(2r+1)^2 // 2``) is the pixel itself."""
    r, c = pix // N_AZIMUTH, pix % N_AZIMUTH
    d = torch.arange(-radius, radius + 1, device=pix.device)
    de, da = torch.meshgrid(d, d, indexing="ij")
    rr = (r[:, None] + de.flatten()[None]).clamp(0, N_ELEVATION - 1)  # [n, K]
    cc = (c[:, None] + da.flatten()[None]) % N_AZIMUTH
    return spectra[bi[:, None], :, rr, cc].permute(0, 2, 1)  # [n, K, L] -> [n, L, K]


class RayNeighborTokens(nn.Module):
    """Per-ray neighbor tokens: ``MLP(map feature ⊕ pixel window ⊕ geometry) -> d``, the geometry's share of the
    first layer computed once per batch (:meth:`geometry`), the rest per ray (:meth:`forward`).

    Args:
        feature_dim: channels of the projected feature map (``k``).
        window: pixel-window radius r (``(2r+1)^2`` values).
        geometry_dim: width of a neighbor's geometry input (PE of its offset + 1 for the distance).
        hidden / d_model: the MLP's hidden and output widths.
    """

    def __init__(self, feature_dim: int, window: int, geometry_dim: int, hidden: int, d_model: int):
        super().__init__()
        self.window = int(window)
        self.ray_in = nn.Linear(feature_dim + (2 * self.window + 1) ** 2, hidden)
        self.geo_in = nn.Linear(geometry_dim, hidden, bias=False)
        self.out = nn.Linear(hidden, d_model)
        self.weight_logits = nn.Linear(hidden, 1)  # ray_knn: per-ray correction of IDW's logits, zero at init
        nn.init.zeros_(self.weight_logits.weight)
        nn.init.zeros_(self.weight_logits.bias)

    def geometry(self, geo: torch.Tensor) -> torch.Tensor:
        """``[B, L, geometry_dim]`` -> the geometry's part of the first layer ``[B, L, hidden]``."""
        return self.geo_in(geo)

    def forward(
        self, feats: torch.Tensor, window: torch.Tensor, geo_part: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``feats [n, L, k]``, ``window [n, L, K]``, ``geo_part [n, L, hidden]`` -> ``(tokens [n, L, d],
        weight logits [n, L])``."""
        return self.from_inputs(torch.cat([feats, window], dim=-1), geo_part)

    def from_inputs(self, inputs: torch.Tensor, geo_part: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward` from its concatenated per-ray inputs ``[n, L, k + K]`` (feature, then window)."""
        h = F.relu(self.ray_in(inputs) + geo_part)
        return self.out(h), self.weight_logits(h).squeeze(-1)


def all_pixel_inputs(maps_padded: torch.Tensor, spectra: torch.Tensor, radius: int) -> torch.Tensor:
    """Every pixel's per-ray inputs at once, ``[B, 90 * 360, L, k + K]`` (pixel-major: a ray's row is one
    contiguous read): :func:`sample_wrap` and :func:`pixel_window` of every pixel of every item, the same values
    (``upsample_wrap`` is ``sample_wrap`` at all pixels).  ``maps_padded [B, L, k, h, w + 2]``, ``spectra [B, L,
    90, 360]``.  For inference over whole spectra, where every pixel is read once."""
    B, L, k, h, w2 = maps_padded.shape
    P = N_ELEVATION * N_AZIMUTH
    feats = upsample_wrap(maps_padded[..., 1:-1].reshape(B * L, k, h, w2 - 2))  # [B L, k, 90, 360]
    feats = feats.view(B, L, k, P).permute(0, 3, 1, 2)  # [B, P, L, k]
    bi = torch.arange(B, device=spectra.device).repeat_interleave(P)
    pix = torch.arange(P, device=spectra.device).repeat(B)
    window = pixel_window(spectra, bi, pix, radius).view(B, P, L, -1)  # [B, P, L, K]
    return torch.cat([feats, window], dim=-1).contiguous()
