"""Localization from spectra (the paper's claim that synthesized spectra initialise a localization model better than
random initialisation): a small CNN from a spectrum to the transmitter's position, and the splits that keep the
test positions out of everything it trains on.

- :class:`SpectrumLocalizer`: ``[B, 90, 360]`` spectra -> ``[B, 3]`` positions in the scene box's normalised
  coordinates ([-1, 1] per axis); azimuth is padded circularly (the spectrum wraps at 360 deg).
- :func:`synthetic_positions`: positions to synthesize spectra at for pre-training, uniform in a box and at least
  ``min_gap`` from every test position, so that no synthesized copy of a test position is trained on.
- :func:`check_disjoint`: refuses a training set with a position within ``min_gap`` of a test position.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from graf.errors import ConfigError


class SpectrumLocalizer(nn.Module):
    """A small CNN: average-pool 2x, three strided convolutions (circular in azimuth), a pooled 3 x 6 map, an MLP."""

    def __init__(self, widths: tuple[int, int, int] = (16, 32, 64), hidden: int = 128):
        super().__init__()
        c1, c2, c3 = widths
        self.convs = nn.ModuleList(
            [nn.Conv2d(1, c1, 5, stride=2), nn.Conv2d(c1, c2, 3, stride=2), nn.Conv2d(c2, c3, 3, stride=2)]
        )
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c3 * 18, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def features(self, spectra: torch.Tensor, layers: int | None = None) -> torch.Tensor:
        """The feature maps after the first ``layers`` convolutions (all by default): ``[B, C, h, w]``."""
        x = F.avg_pool2d(spectra.unsqueeze(1), 2)  # [B, 1, 45, 180]
        for conv in self.convs[:layers]:
            k = conv.kernel_size[0] // 2
            x = F.pad(x, (k, k, 0, 0), mode="circular")  # azimuth wraps
            x = F.pad(x, (0, 0, k, k), mode="replicate")  # elevation does not
            x = F.relu(conv(x))
        return x

    def forward(self, spectra: torch.Tensor) -> torch.Tensor:  # [B, 90, 360] -> [B, 3]
        return self.head(F.adaptive_avg_pool2d(self.features(spectra), (3, 6)))


def normalise(positions, box_min, box_max) -> np.ndarray:
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    return 2.0 * (np.asarray(positions, dtype=np.float64) - lo) / np.maximum(hi - lo, 1e-9) - 1.0


def denormalise(coords, box_min, box_max) -> np.ndarray:
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    return (np.asarray(coords, dtype=np.float64) + 1.0) / 2.0 * (hi - lo) + lo


def _min_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if len(b) == 0:
        return np.full(len(a), np.inf)
    return torch.cdist(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)).amin(1).numpy()


def synthetic_positions(box_min, box_max, n: int, exclude, min_gap: float, seed: int = 0) -> np.ndarray:
    """``n`` positions uniform in the box, each at least ``min_gap`` (m) from every position of ``exclude``
    (the test positions); refused when the box leaves too little room."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    ex = np.asarray(exclude, dtype=np.float64).reshape(-1, 3)
    out: list[np.ndarray] = []
    for _ in range(100):
        cand = rng.uniform(lo, hi, size=(max(2 * n, 64), 3))
        out.append(cand[_min_distance(cand, ex) >= min_gap])
        if sum(len(o) for o in out) >= n:
            return np.concatenate(out)[:n]
    raise ConfigError(
        f"localization: only {sum(len(o) for o in out)} of {n} synthetic positions fit in the box {lo.tolist()} - "
        f"{hi.tolist()} at least {min_gap} m from the {len(ex)} test positions: lower min_gap or n"
    )


def check_disjoint(train_positions, test_positions, min_gap: float, what: str = "training set") -> None:
    """Refuse a training (or synthesized) set with a position closer than ``min_gap`` to a test position."""
    d = _min_distance(np.asarray(train_positions, dtype=np.float64).reshape(-1, 3), np.asarray(test_positions))
    bad = np.flatnonzero(d < min_gap)
    if len(bad):
        raise ConfigError(
            f"localization: the {what} holds {len(bad)} position(s) within {min_gap} m of a test position (first: "
            f"row {int(bad[0])}, {float(d[bad[0]]):.4f} m): a test position or its copy would be trained on"
        )
