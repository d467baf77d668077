"""From a scene's spectra in memory to batches of targets with their neighbours.

A batch (IBRNet/GNT style: source views on one axis with a mask)::

    tgt_index    long  [B]              row of the target in the SpectrumSet
    tgt_id       long  [B]              spectrum id as in the files
    tgt_pos      float [B, 3]
    tgt_spectrum float [B, 90, 360]
    src_index    long  [B, L]           rows of the neighbours (training split only)
    src_pos      float [B, L, 3]
    src_spectra  float [B, L, 90, 360]  gathered from the one in-memory tensor, never stored per ray
    src_mask     bool  [B, L]
    gw_pos       float [B, 3]           gateway (receiver) position
    gw_rot       float [B, 3, 3]        gateway rotation, local -> world (spectrum grid directions are local)
    wavelength   float [B]              of the band (m): GRaF's voxel size
    ray_length   float [B]              farthest corner of the scene's bounds from the gateway (m)
    bounds       float [B, 2, 3]        the scene's axis-aligned box (min, max), for normalising positions
    scene_index  long  [B]              which scene (0 unless several scenes are trained together)

Evaluation neighbours are selected once in :meth:`setup` (deterministic); training neighbours are drawn
per batch with a seeded generator (L uniform in ``L_train``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from graf.bands import Band
from graf.data.nerf2_format import SpectrumSet
from graf.neighbors import NeighborSelector

log = logging.getLogger(__name__)


class _Rows(Dataset):
    def __init__(self, rows: torch.Tensor):
        self.rows = rows

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> int:
        return int(self.rows[i])


class SpectrumDataModule(L.LightningDataModule):
    """Args:
        scene: a scene object (``conf/scene``) with ``load(data_root, band)``.
        band: the :class:`Band`.
        neighbors: the :class:`NeighborSelector`.
        data_root: where datasets are read from and written to.
        batch_size: targets per batch.
        eval_split: ``test`` (default) or ``train`` (each training target with its other neighbours).
        seed: seeds the training-time draw of L and of targets.
    """

    def __init__(self, scene, band: Band, neighbors: NeighborSelector, data_root: str | Path | None = None,
                 batch_size: int = 4, num_workers: int = 0, eval_split: str = "test", seed: int = 0):
        super().__init__()
        if eval_split not in ("test", "train"):
            raise ValueError(f"eval_split must be 'test' or 'train', got {eval_split!r}")
        self.scene, self.band, self.neighbors = scene, band, neighbors
        self.data_root = data_root
        self.batch_size, self.num_workers = int(batch_size), int(num_workers)
        self.eval_split, self.seed = eval_split, int(seed)
        self.data: SpectrumSet | None = None
        self._gen = torch.Generator().manual_seed(self.seed)

    # ------------------------------------------------------------------ setup
    def setup(self, stage: str | None = None) -> None:
        if self.data is None:
            self.data = self.scene.load(self.data_root, self.band)
            d = self.data
            self.positions = torch.as_tensor(d.positions, dtype=torch.float64)
            self.ids = torch.as_tensor(d.ids)
            self.train_rows = torch.as_tensor(d.train_idx)
            self.test_rows = torch.as_tensor(d.test_idx)
            log.info("scene %s: %d train / %d test spectra (%s), band %s (%.4f m)", d.name, d.n_train, d.n_test,
                     d.split_source, self.band.name, self.band.wavelength)
            self._eval_rows = self.test_rows if self.eval_split == "test" else self.train_rows
            from scipy.spatial.transform import Rotation

            self.gw_pos = torch.as_tensor(d.gateway_position, dtype=torch.float32)
            self.gw_rot = torch.as_tensor(Rotation.from_quat(d.gateway_orientation).as_matrix(), dtype=torch.float32)
            b = d.bounds()
            corners = torch.as_tensor([[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
            self.ray_length = float((corners - self.gw_pos.double()).norm(dim=1).max())
            self.bounds = torch.as_tensor(b, dtype=torch.float32)
            nb = self._select(self._eval_rows, train=False)
            self._eval_src = (nb.index, nb.mask)

    def _select(self, rows: torch.Tensor, train: bool):
        nb = self.neighbors.select(
            self.positions[rows], self.positions[self.train_rows], self.band.wavelength, train=train,
            target_ids=self.ids[rows], cand_ids=self.ids[self.train_rows], generator=self._gen,
        )
        nb.index = self.train_rows[nb.index]  # candidate positions -> SpectrumSet rows
        return nb

    @property
    def eval_rows(self) -> torch.Tensor:
        return self._eval_rows

    def eval_neighbors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(src_index [n_eval, L], src_mask [n_eval, L])`` used at evaluation."""
        return self._eval_src

    # ------------------------------------------------------------------ batches
    def make_batch(self, rows: torch.Tensor, src_index: torch.Tensor, src_mask: torch.Tensor) -> dict:
        d = self.data
        return {
            "tgt_index": rows,
            "tgt_id": self.ids[rows],
            "tgt_pos": self.positions[rows].float(),
            "tgt_spectrum": d.spectra[rows],
            "src_index": src_index,
            "src_pos": self.positions[src_index].float(),
            "src_spectra": d.spectra[src_index],
            "src_mask": src_mask,
            "gw_pos": self.gw_pos.expand(len(rows), 3),
            "gw_rot": self.gw_rot.expand(len(rows), 3, 3),
            "wavelength": torch.full((len(rows),), self.band.wavelength, dtype=torch.float32),
            "ray_length": torch.full((len(rows),), self.ray_length, dtype=torch.float32),
            "bounds": self.bounds.expand(len(rows), 2, 3),
            "scene_index": torch.zeros(len(rows), dtype=torch.long),
        }

    def _collate_eval(self, positions: list[int]) -> dict:
        pos = torch.as_tensor(positions, dtype=torch.long)
        idx, mask = self._eval_src
        return self.make_batch(self._eval_rows[pos], idx[pos], mask[pos])

    def _collate_train(self, rows: list[int]) -> dict:
        rows_t = torch.as_tensor(rows, dtype=torch.long)
        nb = self._select(rows_t, train=True)
        return self.make_batch(rows_t, nb.index, nb.mask)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(_Rows(self.train_rows), batch_size=self.batch_size, shuffle=True,
                          generator=torch.Generator().manual_seed(self.seed), collate_fn=self._collate_train,
                          num_workers=self.num_workers, drop_last=len(self.train_rows) > self.batch_size)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(_Rows(torch.arange(len(self._eval_rows))), batch_size=self.batch_size, shuffle=False,
                          collate_fn=self._collate_eval, num_workers=self.num_workers)

    # No val_dataloader: the only held-out spectra are the test split, and choosing checkpoints on them
    # would leak.  Training runs test the final weights.

    def query_batches(self, positions, batch_size: int | None = None):
        """Batches for new transmitter positions ``[N, 3]`` (no measured spectrum: ``tgt_spectrum`` is zeros),
        with neighbours from the training split as at evaluation.  Used by graf-synthesize."""
        pos = torch.as_tensor(positions, dtype=torch.float64)
        nb = self.neighbors.select(pos, self.positions[self.train_rows], self.band.wavelength, train=False)
        src = self.train_rows[nb.index]
        bs = batch_size or self.batch_size
        for s in range(0, len(pos), bs):
            rows = torch.zeros(len(pos[s:s + bs]), dtype=torch.long)
            batch = self.make_batch(rows, src[s:s + bs], nb.mask[s:s + bs])
            batch["tgt_pos"] = pos[s:s + bs].float()
            batch["tgt_spectrum"] = torch.zeros_like(batch["tgt_spectrum"])
            batch["tgt_id"] = torch.arange(s + 1, s + 1 + len(rows))
            yield batch
