"""The NeRF2 network (Zhao et al., MobiCom 2023; layout of XPengZhao/NeRF2 ``model.py``).

Inputs are encoded by :class:`NeRF2Encoding` (10 frequencies plus the raw input: 3 -> 63 dims):

* **attenuation MLP**: ``PE(x)`` through ``depth`` (8) ReLU layers of ``width`` (256), ``PE(x)`` concatenated
  again after the layers listed in ``skips`` (``(4,)``: after the fifth layer, as NeRF2 and NeRF); head
  ``Linear(width, 2)`` -> (attenuation amplitude, attenuation phase) per sample;
* **signal branch**: ``feature = Linear(width, width)`` (no activation), then ``[feature, PE(view), PE(tx)]``
  through ``Linear(width + 63 + 63, width)`` -> ReLU -> ``Linear(width, width // 2)`` -> ReLU ->
  ``Linear(width // 2, 2)`` -> (signal amplitude, signal phase) per sample.

With the defaults this is 690,564 parameters, NeRF2's count.  The view direction is one per ray and the
transmitter one per target, so the signal branch's first layer applies its ``PE(view)`` and ``PE(tx)``
columns once per ray instead of once per sample (the same affine map as NeRF2's concatenation: the
weights keep NeRF2's layout, only the arithmetic is regrouped).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from graf.geometry.encoding import PositionalEncoding


class NeRF2Encoding(PositionalEncoding):
    """NeRF2's embedder: ``[x, sin(2^k x), cos(2^k x)]_{k < F}`` with frequencies ``2^k`` (GRaF's encoding
    uses ``2^k pi``).  The order of the sin/cos columns differs from NeRF2's (grouped by function, not by
    frequency): a fixed permutation of the first layers' input columns, with no effect on what is learned."""

    def __init__(self, num_freqs: int = 10):
        super().__init__(num_freqs, include_input=True)
        self.freqs.copy_(2.0 ** torch.arange(self.num_freqs, dtype=torch.float32))


class NeRF2Network(nn.Module):
    """``forward(pts [..., S, 3], view [..., 3], tx [..., 3]) -> raw [..., S, 4]``.

    ``raw`` holds NeRF2's four outputs per sample: (attenuation amplitude, attenuation phase, signal
    amplitude, signal phase), before the activations of :func:`.renderer.render_rays`.  ``view`` (one per
    ray) and ``tx`` (broadcastable to ``view``) are shared by the ray's S samples.
    """

    def __init__(self, depth: int = 8, width: int = 256, skips: Sequence[int] = (4,), pe_freqs: int = 10):
        super().__init__()
        if depth < 1 or width < 2:
            raise ValueError(f"model.depth must be >= 1 and model.width >= 2, got {depth} and {width}")
        self.skips = tuple(int(s) for s in skips)
        if any(not 0 <= s < depth - 1 for s in self.skips):
            raise ValueError(f"model.skips must index hidden layers 0..{depth - 2} (depth={depth}), got {skips}")
        self.pe = NeRF2Encoding(pe_freqs)
        pe_dim = self.pe.out_dim(3)
        self.attenuation = nn.ModuleList(
            [nn.Linear(pe_dim, width)]
            + [nn.Linear(width + pe_dim if i - 1 in self.skips else width, width) for i in range(1, depth)]
        )
        self.attenuation_out = nn.Linear(width, 2)
        self.feature = nn.Linear(width, width)
        self.signal = nn.ModuleList([nn.Linear(width + 2 * pe_dim, width), nn.Linear(width, width // 2)])
        self.signal_out = nn.Linear(width // 2, 2)
        self.width = int(width)

    def forward(self, pts: torch.Tensor, view: torch.Tensor, tx: torch.Tensor) -> torch.Tensor:
        pe_pts = self.pe(pts)  # [..., S, 63]
        x = pe_pts
        for i, layer in enumerate(self.attenuation):
            x = F.relu(layer(x), inplace=True)
            if i in self.skips:
                x = torch.cat([pe_pts, x], dim=-1)
        attenuation = self.attenuation_out(x)  # [..., S, 2]
        first = self.signal[0]
        w_feat, w_ray = first.weight[:, : self.width], first.weight[:, self.width :]
        per_ray = torch.cat([self.pe(view), self.pe(tx).expand(*view.shape[:-1], -1)], dim=-1)  # [..., 126]
        per_ray = F.linear(per_ray, w_ray, first.bias)  # [..., width]
        x = F.relu(F.linear(self.feature(x), w_feat) + per_ray.unsqueeze(-2), inplace=True)
        x = F.relu(self.signal[1](x), inplace=True)
        return torch.cat([attenuation, self.signal_out(x)], dim=-1)  # [..., S, 4]
