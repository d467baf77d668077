"""The dataset type every scene loads into (real folders and simulated files alike), and the error that
names a bad input file.

A :class:`SpectrumSet` is one scene's measurements held once in memory; :class:`graf.data.datamodule.
SpectrumDataModule` turns one or several of them into batches.  Readers (:mod:`graf.data.nerf2_format`,
:mod:`graf.sim.dataset`) produce it.
"""

from __future__ import annotations

import logging
import os
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from graf.bands import SPEED_OF_LIGHT
from graf.errors import UserError

log = logging.getLogger(__name__)


class DataFormatError(UserError):
    """A scene's files (or a data setting) are not as expected.  The message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


@dataclass
class SpectrumSet:
    """A scene's measurements held once in memory.

    Attributes:
        spectra: float32 ``[N, 90, 360]`` in [0, 1]; row r is elevation r+1 deg, column c azimuth c+1 deg.
        positions: float64 ``[N, 3]`` transmitter positions (m).
        ids: int64 ``[N]`` spectrum ids as in the files.
        train_idx / test_idx: int64 row indices into the arrays above (disjoint).
        gateway_position: ``[3]``; gateway_orientation: quaternion ``[4]`` in (x, y, z, w) order.
    """

    name: str
    spectra: torch.Tensor
    positions: np.ndarray
    ids: np.ndarray
    train_idx: np.ndarray
    test_idx: np.ndarray
    gateway_position: np.ndarray
    gateway_orientation: np.ndarray
    frequency_hz: float
    source: str
    split_source: str
    meta: dict = field(default_factory=dict)

    @property
    def wavelength(self) -> float:
        return SPEED_OF_LIGHT / self.frequency_hz

    @property
    def n_train(self) -> int:
        return int(len(self.train_idx))

    @property
    def n_test(self) -> int:
        return int(len(self.test_idx))

    def bounds(self) -> np.ndarray:
        """Axis-aligned box ``[2, 3]`` holding every transmitter and the gateway (a real scene's only
        known geometry); simulated scenes carry their room bounds instead in ``meta['bounds']``."""
        if "bounds" in self.meta:
            return np.asarray(self.meta["bounds"], dtype=np.float64)
        pts = np.vstack([self.positions, self.gateway_position[None]])
        return np.stack([pts.min(0), pts.max(0)])


def warn_flat_spectra(spectra: torch.Tensor, ids, source: str | os.PathLike) -> list[int]:
    """Warn about spectra that are constant (max == min, all-zero included) and return their ids.

    Such a spectrum is valid data (metrics handle it) but carries no direction information, so it is
    worth knowing about: one :class:`UserWarning` and one log warning name ``source`` and the ids (the
    first 10 and a count when there are more).  ``spectra`` is ``[N, 90, 360]``, ``ids`` has N entries.
    """
    spectra = torch.as_tensor(spectra)
    if spectra.ndim != 3 or len(spectra) == 0:
        return []
    flat_rows = spectra.flatten(1)
    lo, hi = flat_rows.amin(dim=1), flat_rows.amax(dim=1)
    rows = torch.nonzero(hi == lo).flatten().tolist()
    if not rows:
        return []
    ids = np.asarray(ids).reshape(-1)
    flat_ids = [int(ids[r]) for r in rows]
    values = sorted({round(float(lo[r]), 3) for r in rows})
    shown = flat_ids[:10]
    if len(flat_ids) == 1:
        which = f"spectrum id {shown[0]} is"
    elif len(flat_ids) <= 10:
        which = f"spectrum ids {shown} are"
    else:
        which = f"spectrum ids {shown} and {len(flat_ids) - 10} more ({len(flat_ids)} in all) are"
    if len(values) == 1:
        level = f"all {values[0]:.3f}"
    else:
        level = "values " + ", ".join(f"{v:.3f}" for v in values[:5]) + (", ..." if len(values) > 5 else "")
    carry = "it carries" if len(flat_ids) == 1 else "they carry"
    message = f"{source}: {which} constant ({level}): {carry} no direction information"
    log.warning("%s", message)
    warnings.warn(message, UserWarning, stacklevel=3)
    return flat_ids
