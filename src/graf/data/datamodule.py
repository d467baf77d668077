"""From scenes' spectra in memory to batches of targets with their neighbors.

A batch (IBRNet/GNT style: source views on one axis with a mask)::

    tgt_index    long  [B]              row of the target in the datamodule's concatenated spectra
    tgt_id       long  [B]              spectrum id as in the scene's files
    tgt_pos      float [B, 3]
    tgt_spectrum float [B, 90, 360]
    src_index    long  [B, L]           rows of the neighbors (always of the target's own scene)
    src_pos      float [B, L, 3]
    src_spectra  float [B, L, 90, 360]  gathered from the one in-memory tensor, never stored per ray
    src_mask     bool  [B, L]
    gw_pos       float [B, 3]           the item's gateway (receiver) position
    gw_rot       float [B, 3, 3]        its gateway rotation, local -> world (spectrum grid directions are local)
    wavelength   float [B]              of the item's band (m): GRaF's voxel size
    ray_length   float [B]              farthest corner of the item's scene bounds from its gateway (m)
    bounds       float [B, 2, 3]        the item's scene box (min, max)
    scene_index  long  [B]              the item's scene index (a model's 4-D positions): its position in the
                                        list of scenes, or ``scene_indices[k]`` when given (a test scene
                                        keeps the index it was trained with; an unseen one the first index it
                                        was not trained with: graf.data.fingerprint.eval_scene_index)

Every per-item geometry value is gathered through the item's scene index from per-scene tables, so scenes
of different sizes and bands can share a batch (:mod:`graf.data.scene_rows`).  The splits and what each
one's neighbors are drawn from: :mod:`graf.data.splits`; the training stream (a batch is a pure function of
the seed and its number, so a resumed run draws what an uninterrupted one would): :mod:`graf.data.loaders`.

**Set-up checks what the stage selects.**  ``setup(stage)`` checks that every target the stage will select
has a neighbor (:meth:`~graf.data.scene_rows.SceneRows.stage_splits`): a training run all of them before it
starts, an evaluation only the validation split and the evaluated one (its training targets are never
selected, so a training split too small for the run's sparse neighbors does not refuse it).
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from graf.bands import Band
from graf.config_home import defaults_from
from graf.data.loaders import Positions, StepLoader, TrainBatchStream
from graf.data.neighbors import NeighborSelector
from graf.data.scene_rows import SceneRows
from graf.data.spectrum_set import SpectrumSet
from graf.data.splits import EVAL_SPLITS, TEST_POOLS, derangement, mixed_seed
from graf.errors import ConfigError


@defaults_from("data/default.yaml")
class SpectrumDataModule(SceneRows, L.LightningDataModule):
    """Args:
    scene: a scene object (``conf/scene``) with ``load(data_root, band)``, or a list of them (trained
        together; each batch item keeps its own scene's geometry and band).
    band: the :class:`Band`, or a list (one per scene).
    neighbors: the :class:`NeighborSelector`.
    data_root: where datasets are read from and written to.
    batch_size: targets per batch.
    eval_split: what ``test_dataloader`` evaluates: ``test`` (default), ``val``, or ``train`` (each fit
        target with its other fit neighbors).
    seed: seeds the training stream (target order, L and neighbor draws).
    val_fraction / val_seed: the validation part of each scene's training split (seeded by ``val_seed``,
        independent of ``seed``).
    scene_indices: the scene index each scene's items carry (default ``0 .. n_scenes - 1``).
    measured_fraction: the part of each scene's training split that is measured (null: all of it).
    measured_seed: draws the measured part.
    test_pool: where test neighbors come from: ``measured`` (the measured part: default) or
        ``train_split`` (the whole training split, measured or not).
    simulate_missing: a simulated scene whose dataset file is missing is ray-traced first (studies).
    test_subset / test_subset_seed: test at most ``test_subset`` spectra of each scene's test split, a subset
        drawn by ``test_subset_seed`` (independent of ``seed``: the same subset for every method, training seed
        and neighbor count of a study; null: the first ``test_subset`` of the split); ``test_subset`` null: the
        whole test split.  The one setting of how many spectra a run tests.
    """

    def __init__(
        self,
        scene,
        band: Band | Sequence[Band],
        neighbors: NeighborSelector,
        data_root: str | Path | None = None,
        *,
        batch_size: int,
        num_workers: int,
        eval_split: str,
        seed: int = 0,
        val_fraction: float,
        val_seed: int,
        scene_indices: Sequence[int] | None = None,
        measured_fraction: float | None = None,
        measured_seed: int = 0,
        test_pool: str = "measured",
        simulate_missing: bool,
        test_subset: int | None,
        test_subset_seed: int,
    ):
        super().__init__()
        if test_subset is not None and (isinstance(test_subset, bool) or int(test_subset) < 1):
            raise ConfigError(f"data.test_subset must be a positive integer or null, got {test_subset!r}")
        self.test_subset = None if test_subset is None else int(test_subset)
        self.test_subset_seed = None if test_subset_seed is None else int(test_subset_seed)
        if test_pool not in TEST_POOLS:
            raise ConfigError(f"finetune.test_pool must be one of {TEST_POOLS}, got {test_pool!r}")
        if measured_fraction is not None and not 0.0 < float(measured_fraction) <= 1.0:
            raise ConfigError(f"finetune.fraction (the measured fraction) must be in (0, 1], got {measured_fraction}")
        self.measured_fraction = None if measured_fraction is None else float(measured_fraction)
        self.measured_seed, self.test_pool = int(measured_seed), test_pool
        self.simulate_missing = bool(simulate_missing)
        if eval_split not in EVAL_SPLITS:
            raise ConfigError(f"data.eval_split must be one of {', '.join(EVAL_SPLITS)}, got {eval_split!r}")
        for key, value, low in (("batch_size", batch_size, 1), ("num_workers", num_workers, 0)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
                raise ConfigError(f"data.{key} must be an integer >= {low}, got {value!r}")
        self.scenes = list(scene) if isinstance(scene, (list, tuple)) else [scene]
        bands = list(band) if isinstance(band, (list, tuple)) else [band] * len(self.scenes)
        if len(bands) != len(self.scenes):
            raise ValueError(f"{len(bands)} bands given for {len(self.scenes)} scenes")
        self.bands, self.band, self.neighbors = bands, bands[0], neighbors
        self.data_root = data_root
        self.batch_size, self.num_workers = int(batch_size), int(num_workers)
        self.eval_split, self.seed = eval_split, int(seed)
        self.val_fraction, self.val_seed = float(val_fraction), int(val_seed)
        self.sets: list[SpectrumSet] = []
        idx = list(range(len(self.scenes))) if scene_indices is None else [int(i) for i in scene_indices]
        if len(idx) != len(self.scenes):
            raise ValueError(f"{len(idx)} scene indices given for {len(self.scenes)} scenes")
        self.scene_index = torch.as_tensor(idx, dtype=torch.long)
        self.swap_seed: int | None = None  # set by the reliance pass (swapped_neighbors)
        self.scene_index_source = "trained"  # how the scene index was given (graf.data.fingerprint.eval_scene_index)

    # ------------------------------------------------------------------ setup
    def setup(self, stage: str | None = None) -> None:
        """Load the scenes (once), then check that every target ``stage`` will select has a neighbor
        (:meth:`~graf.data.scene_rows.SceneRows.stage_splits`; each split is checked once)."""
        if not self.sets:
            self.load_scenes()
            self._eval = {}
        self.check_neighbors(self.stage_splits(stage))

    # ------------------------------------------------------------------ evaluation splits
    def split_neighbors(self, name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(rows [n], src_index [n, L], src_mask [n, L])`` of evaluation split ``name`` (selected once)."""
        if name not in self._eval:
            rows, pool = self.split_rows(name)
            nb = self.select(rows, pool, train=False)
            self._eval[name] = (rows, nb.index, nb.mask)
        return self._eval[name]

    @property
    def eval_rows(self) -> torch.Tensor:
        return self.split_neighbors(self.eval_split)[0]

    def nearest_neighbor_used(self, name: str | None = None) -> dict | None:
        """The geometry of evaluation split ``name`` (default: the one tested) as its methods see it: the median over
        its targets of the distance to the nearest neighbor actually used (after ``neighbors.exclude_within``), in
        metres and in wavelengths of each target's band; None without a target that has a neighbor."""
        rows, index, mask = self.split_neighbors(name or self.eval_split)
        if len(rows) == 0 or not bool(mask.any()):
            return None
        d = torch.linalg.vector_norm(self.positions[index].double() - self.positions[rows][:, None].double(), dim=-1)
        nearest = d.masked_fill(~mask.bool(), float("inf")).min(dim=1).values
        wavelengths = nearest / self.wavelength[self.row_scene[rows]].double()
        found = torch.isfinite(nearest)
        return {
            "median_m": round(float(nearest[found].median()), 6),
            "median_wavelengths": round(float(wavelengths[found].median()), 4),
            "n_targets": int(found.sum()),
        }

    def split_summary(self) -> dict:
        """What results.json records about the splits, with the tested split's neighbor geometry
        (:meth:`nearest_neighbor_used`)."""
        return {**super().split_summary(), "nearest_neighbor_used": self.nearest_neighbor_used()}

    def eval_neighbors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(src_index [n_eval, L], src_mask [n_eval, L])`` used by ``test_dataloader``."""
        return self.split_neighbors(self.eval_split)[1:]

    # ------------------------------------------------------------------ batches
    def make_batch(self, rows: torch.Tensor, src_index: torch.Tensor, src_mask: torch.Tensor) -> dict:
        rows = torch.as_tensor(rows, dtype=torch.long)
        k = self.row_scene[rows]
        return {
            "tgt_index": rows,
            "tgt_id": self.ids[rows],
            "tgt_pos": self.positions[rows].float(),
            "tgt_spectrum": self.spectra[rows],
            "src_index": src_index,
            "src_pos": self.positions[src_index].float(),
            "src_spectra": self.spectra[src_index],
            "src_mask": src_mask,
            "gw_pos": self.gw_pos[k],
            "gw_rot": self.gw_rot[k],
            "wavelength": self.wavelength[k],
            "ray_length": self.ray_length[k],
            "bounds": self.bounds[k],
            "scene_index": self.scene_index[k],
        }

    def swapped_neighbors(self, name: str, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """``split_neighbors(name)`` with each target's neighbors replaced by another target's of the same scene
        (a seeded derangement: no target keeps its own, every list is some target's, the same L): what a model
        that reads its neighbors must do worse on (:func:`graf.metrics.reliance.neighbor_reliance`).  None when
        a scene has a single target in the split (no derangement exists)."""
        rows, idx, mask = self.split_neighbors(name)
        perm = torch.arange(len(rows))
        rng = np.random.default_rng(int(seed))
        for k in torch.unique(self.row_scene[rows]).tolist():
            members = (self.row_scene[rows] == k).nonzero().flatten()
            if len(members) < 2:
                return None
            perm[members] = members[torch.as_tensor(derangement(len(members), rng))]
        return rows, idx[perm], mask[perm]

    def _eval_collate(self, name: str):
        rows, idx, mask = self.split_neighbors(name)
        if self.swap_seed is not None:  # the reliance pass: every target with another target's neighbors
            swapped = self.swapped_neighbors(name, self.swap_seed)
            if swapped is None:
                raise ValueError(f"split {name}: a scene has a single target, no derangement of its neighbors")
            rows, idx, mask = swapped

        def collate(positions: list[int]) -> dict:
            pos = torch.as_tensor(positions, dtype=torch.long)
            return self.make_batch(rows[pos], idx[pos], mask[pos])

        return collate

    def eval_batch(self, positions: list[int]) -> dict:
        """The batch ``test_dataloader`` makes of the evaluated split's targets at ``positions``."""
        return self._eval_collate(self.eval_split)(positions)

    @property
    def batches_per_epoch(self) -> int:
        n = len(self.fit_rows)
        return max(1, n // self.batch_size) if n > self.batch_size else 1

    def _rank(self) -> tuple[int, int]:
        """``(global rank, world size)`` of the trainer this datamodule is attached to ((0, 1) without one)."""
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 0, 1
        return int(trainer.global_rank), int(trainer.world_size)

    def train_batch(self, k: int) -> dict:
        """Training batch number ``k`` of the stream: targets from epoch ``k // batches_per_epoch``'s seeded order,
        and L and neighbors drawn with a generator seeded by ``(seed, k)``.  Under data-parallel training the
        loader asks for :meth:`rank_batch` instead."""
        epoch, j = divmod(int(k), self.batches_per_epoch)
        order = torch.randperm(
            len(self.fit_rows), generator=torch.Generator().manual_seed(mixed_seed(self.seed, 0, epoch))
        )
        rows = self.fit_rows[order[j * self.batch_size : (j + 1) * self.batch_size]]
        nb = self.select(
            rows, self.fit_rows, train=True, generator=torch.Generator().manual_seed(mixed_seed(self.seed, 1, k))
        )
        return self.make_batch(rows, nb.index, nb.mask)

    def _global_step(self) -> int:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 0
        if int(getattr(trainer, "accumulate_grad_batches", 1)) != 1:
            raise ValueError("trainer.accumulate_grad_batches must be 1: training batches are numbered by step")
        return int(trainer.global_step)

    def rank_batch(self, k: int) -> dict:
        """Step ``k``'s batch on this rank: the stream's draw ``k * world_size + rank`` (one process: draw ``k``),
        so the ranks of a step train on different draws and a resumed run draws what an uninterrupted one would."""
        rank, world = self._rank()
        return self.train_batch(int(k) * world + rank)

    def train_dataloader(self) -> DataLoader:
        return StepLoader(
            TrainBatchStream(self.batches_per_epoch),
            self._global_step,
            self.seed,
            collate_fn=self.rank_batch,
            num_workers=self.num_workers,
        )

    def eval_positions(self, n: int) -> list[int]:
        """This rank's share of an evaluation split's ``n`` positions: every ``world_size``-th from its rank, so
        each spectrum is evaluated once (no padding) and the metrics' sums add up across ranks."""
        rank, world = self._rank()
        return list(range(rank, n, world))

    def _eval_loader(self, name: str) -> DataLoader:
        rows = self.split_neighbors(name)[0]
        share = self.eval_positions(len(rows))
        return DataLoader(
            share if len(share) < len(rows) else Positions(len(rows)),
            batch_size=self.batch_size,
            shuffle=False,
            collate_fn=self._eval_collate(name),
            num_workers=self.num_workers,
        )

    def val_dataloader(self) -> DataLoader:
        return self._eval_loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader(self.eval_split)

    def query_batches(self, positions, batch_size: int | None = None):
        """Batches for new transmitter positions ``[N, 3]`` of the (single) scene (no measured spectrum:
        ``tgt_spectrum`` is zeros), with neighbors from the training split as at test.  Used by graf-synthesize."""
        pos = torch.as_tensor(positions, dtype=torch.float64)
        pool = self.split_rows("test")[1]
        nb = self.neighbors.select(pos, self.positions[pool], self.band.wavelength, train=False)
        src = pool[nb.index]
        bs = batch_size or self.batch_size
        for s in range(0, len(pos), bs):
            rows = torch.zeros(len(pos[s : s + bs]), dtype=torch.long)
            batch = self.make_batch(rows, src[s : s + bs], nb.mask[s : s + bs])
            batch["tgt_pos"] = pos[s : s + bs].float()
            batch["tgt_spectrum"] = torch.zeros_like(batch["tgt_spectrum"])
            batch["tgt_id"] = torch.arange(s + 1, s + 1 + len(rows))
            yield batch
