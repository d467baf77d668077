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
                                        keeps the index it was trained with; an unseen one gets a new one)

Every per-item geometry value is gathered through the item's scene index from per-scene tables, so scenes
of different sizes and bands can share a batch.

**Splits.**  Each scene's training split (from its files) is cut, with a seeded permutation
(``val_seed``, the same whatever the run's ``seed``), into a *validation* part (``val_fraction`` of it, at
least one spectrum) and the *fit* part (the rest):

- training targets and their neighbors: fit spectra only (never the target itself);
- validation targets: the validation spectra, neighbors from the fit spectra only (so nothing a model is
  chosen on was trained on, and validation conditions match training);
- test targets: the test split, neighbors from the whole training split (fit + validation: at test time
  every measured spectrum is known).

The validation and test splits never share a spectrum; nothing is ever chosen on the test split.

**Measured fraction** (fine-tuning, ``conf/finetune``).  With ``measured_fraction`` (e.g. 0.2), only a seeded
part of each scene's training split counts as measured (``measured_seed``; at least 2 spectra, else an error):
the validation and fit parts are cut from it, and it is the pool test neighbors come from.  With
``test_pool="train_split"`` test neighbors come from the whole training split instead (the seed's zero-shot
protocol), while fitting still sees the measured part only.  The test split is never touched.

**Training batches are a pure function of (seed, batch number).**  Batch ``k`` belongs to epoch
``k // batches_per_epoch``, whose order is a permutation seeded by ``(seed, epoch)``; its neighbor
counts and draws come from a generator seeded by ``(seed, k)``.  The loader starts at the trainer's
``global_step``, so a run resumed from a checkpoint draws exactly the batches an uninterrupted run would,
and with ``num_workers > 0`` worker ``w`` builds batches ``k = w, w + W, ...`` (no shared generator, no
identical draws across workers, the same stream for every worker count).
"""

from __future__ import annotations

import logging
import numbers
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info

from graf.bands import Band
from graf.data.neighbors import Neighbors, NeighborSelector, NoNeighborsError
from graf.data.spectrum_set import DataFormatError, SpectrumSet
from graf.errors import ConfigError

log = logging.getLogger(__name__)

EVAL_SPLITS = ("test", "val", "train")
TEST_POOLS = ("measured", "train_split")


def measured_part(train_rows: np.ndarray, fraction: float | None, seed: int, where: str) -> np.ndarray:
    """The seeded ``fraction`` of ``train_rows`` that is measured (rounded, at least 2: one to validate on, one
    to fit and take neighbors from); all of them when ``fraction`` is None."""
    n = len(train_rows)
    if fraction is None or fraction >= 1.0:
        return np.sort(train_rows)
    k = int(round(n * fraction))
    if k < 2:
        raise DataFormatError(
            where,
            f"a measured fraction of {fraction:g} of its {n} training spectra leaves {k}: at "
            "least 2 are needed (one to validate on, one to fit and take neighbors from); "
            "use a larger fraction or more spectra",
        )
    perm = np.random.default_rng(int(seed)).permutation(n)
    return np.sort(train_rows[perm[:k]])


def derangement(n: int, rng: np.random.Generator) -> np.ndarray:
    """A seeded permutation of ``range(n)`` with no fixed point (n >= 2): a uniform random n-cycle (Sattolo's
    algorithm)."""
    p = np.arange(n)
    for i in range(n - 1, 0, -1):
        j = int(rng.integers(0, i))  # j < i: never i itself
        p[i], p[j] = p[j], p[i]
    return p


def mixed_seed(*parts: int) -> int:
    """A 63-bit seed from integers (numpy's SeedSequence: well mixed, stable across versions)."""
    state = np.random.SeedSequence([int(p) & 0xFFFFFFFF for p in parts]).generate_state(1, np.uint64)[0]
    return int(state) & 0x7FFFFFFFFFFFFFFF


def carve_validation(train_rows: np.ndarray, fraction: float, seed: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``(fit_rows, val_rows)``: a seeded ``fraction`` (rounded, at least 1) of ``train_rows`` for validation."""
    n = len(train_rows)
    if not 0.0 < fraction < 1.0:
        raise ConfigError(
            f"data.val_fraction must be in (0, 1), got {fraction}: validation is carved from each "
            "scene's training split (at least one spectrum), so 0 and 1 leave nothing to validate or fit on"
        )
    if n < 2:
        raise DataFormatError(
            where,
            f"the training split holds {n} spectrum(s): at least 2 are needed, one to "
            "validate on and one to train on and take neighbors from",
        )
    n_val = min(max(int(round(n * fraction)), 1), n - 1)
    perm = np.random.default_rng(int(seed)).permutation(n)
    return np.sort(train_rows[perm[n_val:]]), np.sort(train_rows[perm[:n_val]])


class _Positions(Dataset):
    """Map-style dataset of positions 0..n-1 into a split's rows (evaluation)."""

    def __init__(self, n: int):
        self.n = int(n)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        return int(i)


class TrainBatchStream(IterableDataset):
    """Batch numbers ``start, start + 1, ...`` up to the end of ``start``'s epoch (``__len__``: one epoch).

    Each worker yields its share (``k % num_workers == worker id``); the DataLoader interleaves them back in
    order.  The batch itself is built by the loader's ``collate_fn`` from ``k`` alone."""

    def __init__(self, batches_per_epoch: int):
        self.batches_per_epoch = int(batches_per_epoch)
        self.start = 0

    def __len__(self) -> int:
        return self.batches_per_epoch

    def __iter__(self):
        info = get_worker_info()
        wid, nw = (0, 1) if info is None else (info.id, info.num_workers)
        end = (self.start // self.batches_per_epoch + 1) * self.batches_per_epoch
        return iter(range(self.start + wid, end, nw))


class StepLoader(DataLoader):
    """The training loader: sets the stream's first batch number from ``step_source()`` (the trainer's
    global step) every time it is iterated.  Its ``state_dict`` (saved in Lightning checkpoints) records the
    seed and batch number, and a resumed run with another seed is warned about."""

    def __init__(self, stream: TrainBatchStream, step_source: Callable[[], int], seed: int, **kwargs):
        super().__init__(stream, batch_size=None, shuffle=False, **kwargs)
        self.step_source, self.seed = step_source, int(seed)

    def __iter__(self):
        self.dataset.start = int(self.step_source())
        return super().__iter__()

    def state_dict(self) -> dict:
        return {"seed": self.seed, "next_batch": int(self.step_source()), "stream": "step-indexed"}

    def load_state_dict(self, state: dict) -> None:
        if int(state.get("seed", self.seed)) != self.seed:
            warnings.warn(
                f"resuming a run trained with data seed {state['seed']} with seed {self.seed}: the "
                "batches after the checkpoint differ from an uninterrupted run",
                stacklevel=2,
            )


class SpectrumDataModule(L.LightningDataModule):
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
    """

    def __init__(
        self,
        scene,
        band: Band | Sequence[Band],
        neighbors: NeighborSelector,
        data_root: str | Path | None = None,
        batch_size: int = 4,
        num_workers: int = 0,
        eval_split: str = "test",
        seed: int = 0,
        val_fraction: float = 0.1,
        val_seed: int = 0,
        scene_indices: Sequence[int] | None = None,
        measured_fraction: float | None = None,
        measured_seed: int = 0,
        test_pool: str = "measured",
        simulate_missing: bool = False,
    ):
        super().__init__()
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

    # ------------------------------------------------------------------ setup
    def setup(self, stage: str | None = None) -> None:
        if self.sets:
            return
        from scipy.spatial.transform import Rotation

        if self.simulate_missing:
            for s, b in zip(self.scenes, self.bands):
                if hasattr(s, "ensure_dataset"):
                    s.ensure_dataset(self.data_root, b)
        self.sets = [s.load(self.data_root, b) for s, b in zip(self.scenes, self.bands)]
        spectra, pos, ids, scene_of = [], [], [], []
        splits = {"train": [], "measured": [], "fit": [], "val": [], "test": []}
        gw_pos, gw_rot, wl, ray_len, bounds = [], [], [], [], []
        offset = 0
        for k, (d, band) in enumerate(zip(self.sets, self.bands)):
            n = len(d.ids)
            train = np.asarray(d.train_idx, np.int64) + offset
            measured = measured_part(train, self.measured_fraction, self.measured_seed, d.source)
            fit, val = carve_validation(measured, self.val_fraction, self.val_seed, d.source)
            splits["train"].append(train), splits["measured"].append(measured)
            splits["fit"].append(fit), splits["val"].append(val)
            splits["test"].append(np.asarray(d.test_idx, np.int64) + offset)
            spectra.append(d.spectra), pos.append(np.asarray(d.positions, np.float64))
            ids.append(np.asarray(d.ids, np.int64)), scene_of.append(np.full(n, k, np.int64))
            p = torch.as_tensor(d.gateway_position, dtype=torch.float64)
            b = torch.as_tensor(d.bounds(), dtype=torch.float64)
            corners = torch.stack(
                [torch.stack([b[i, 0], b[j, 1], b[m, 2]]) for i in (0, 1) for j in (0, 1) for m in (0, 1)]
            )
            gw_pos.append(p), bounds.append(b), wl.append(band.wavelength)
            gw_rot.append(torch.as_tensor(Rotation.from_quat(d.gateway_orientation).as_matrix()))
            ray_len.append(float((corners - p).norm(dim=1).max()))
            log.info(
                "scene %s (index %d): %d train (%s%d fit + %d validation) / %d test spectra (%s), band %s (%.4f m)",
                d.name,
                int(self.scene_index[k]),
                d.n_train,
                "" if len(measured) == len(train) else f"{len(measured)} measured: ",
                len(fit),
                len(val),
                d.n_test,
                d.split_source,
                band.name,
                band.wavelength,
            )
            offset += n
        self.spectra = spectra[0] if len(spectra) == 1 else torch.cat(spectra)
        self.positions = torch.as_tensor(np.concatenate(pos))
        self.ids = torch.as_tensor(np.concatenate(ids))
        self.row_scene = torch.as_tensor(np.concatenate(scene_of))
        self.train_rows, self.measured_rows, self.fit_rows, self.val_rows, self.test_rows = (
            torch.as_tensor(np.concatenate(splits[s])) for s in ("train", "measured", "fit", "val", "test")
        )
        # per-scene tables, gathered per batch item through its scene index
        self.gw_pos = torch.stack(gw_pos).float()
        self.gw_rot = torch.stack(gw_rot).float()
        self.wavelength = torch.as_tensor(wl, dtype=torch.float32)
        self.ray_length = torch.as_tensor(ray_len, dtype=torch.float32)
        self.bounds = torch.stack(bounds).float()
        self._eval = {}
        self.check_neighbors()

    def check_neighbors(self) -> None:
        """Every target of every split has at least one neighbor under the run's selector (``exclude_within``
        drops the nearest ones): checked once at set-up, so a setting that leaves a target with none is one
        clear error before any training or evaluation starts, not a failure deep inside a loader."""
        for name in ("train", "val", "test"):
            rows, pool = self._split(name)
            for s in range(0, len(rows), 1024):
                self.select(rows[s : s + 1024], pool, train=False, quiet=True)

    def set_scene_indices(self, indices: Sequence[int]) -> None:
        """The scene index each scene's items carry (decided by content after set-up: see
        :mod:`graf.data.fingerprint`)."""
        idx = [int(i) for i in indices]
        if len(idx) != len(self.scenes):
            raise ValueError(f"{len(idx)} scene indices given for {len(self.scenes)} scenes")
        if idx != self.scene_index.tolist():
            log.info("scene indices: %s", ", ".join(f"{d.name} {i}" for d, i in zip(self.sets, idx)))
        self.scene_index = torch.as_tensor(idx, dtype=torch.long)

    def fingerprints(self) -> list[dict]:
        """Each scene's content fingerprint at its band (:func:`graf.data.fingerprint.scene_fingerprint`)."""
        from graf.data.fingerprint import scene_fingerprint

        return [scene_fingerprint(d, b.frequency_hz) for d, b in zip(self.sets, self.bands)]

    @property
    def data(self) -> SpectrumSet:
        """The scene's :class:`SpectrumSet` (single-scene runs; see :attr:`sets` for several)."""
        if len(self.sets) != 1:
            raise AttributeError(f"this datamodule holds {len(self.sets)} scenes: use .sets")
        return self.sets[0]

    @property
    def scene_name(self) -> str:
        return "+".join(d.name for d in self.sets)

    @property
    def n_train(self) -> int:
        return int(len(self.train_rows))

    # ------------------------------------------------------------------ neighbors
    def select(
        self,
        rows: torch.Tensor,
        pool: torch.Tensor,
        train: bool,
        generator: torch.Generator | None = None,
        quiet: bool = False,
    ) -> Neighbors:
        """Neighbors of ``rows`` among ``pool`` (both datamodule rows), each target's from its own scene only,
        never the target itself; indices returned as datamodule rows."""
        rows, pool = torch.as_tensor(rows, dtype=torch.long), torch.as_tensor(pool, dtype=torch.long)
        parts = []
        for k in torch.unique(self.row_scene[rows]).tolist():
            t = (self.row_scene[rows] == k).nonzero().flatten()
            cand = pool[self.row_scene[pool] == k]
            if len(cand) == 0:
                raise DataFormatError(self.sets[k].source, "no spectra left to take neighbors from")
            try:
                nb = self.neighbors.select(
                    self.positions[rows[t]],
                    self.positions[cand],
                    float(self.wavelength[k]),
                    train=train,
                    target_ids=self.ids[rows[t]],
                    cand_ids=self.ids[cand],
                    generator=generator,
                    quiet=quiet,
                )
            except NoNeighborsError as exc:
                raise NoNeighborsError(
                    f"scene {self.sets[k].name}: {exc} (neighbors.exclude_within={self.neighbors.exclude_within:g} "
                    f"wavelengths of {float(self.wavelength[k]):.4g} m): lower neighbors.exclude_within, or use more "
                    "training spectra"
                ) from None
            nb.index = cand[nb.index]
            parts.append((t, nb))
        if len(parts) == 1:
            return parts[0][1]
        T, Lmax = len(rows), max(nb.index.shape[1] for _, nb in parts)
        out = Neighbors(
            index=torch.zeros(T, Lmax, dtype=torch.long),
            mask=torch.zeros(T, Lmax, dtype=torch.bool),
            distance=torch.zeros(T, Lmax, dtype=self.positions.dtype),
            widened=torch.zeros(T, dtype=torch.bool),
            short=torch.zeros(T, dtype=torch.bool),
        )
        for t, nb in parts:
            w = nb.index.shape[1]
            out.index[t, :w], out.mask[t, :w], out.distance[t, :w] = nb.index, nb.mask, nb.distance
            out.widened[t], out.short[t] = nb.widened, nb.short
        return out

    def _split(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """``(target rows, neighbor pool)`` of an evaluation split."""
        pool = self.measured_rows if self.test_pool == "measured" else self.train_rows
        return {
            "test": (self.test_rows, pool),
            "val": (self.val_rows, self.fit_rows),
            "train": (self.fit_rows, self.fit_rows),
        }[name]

    def split_neighbors(self, name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(rows [n], src_index [n, L], src_mask [n, L])`` of evaluation split ``name`` (selected once)."""
        if name not in self._eval:
            rows, pool = self._split(name)
            nb = self.select(rows, pool, train=False)
            self._eval[name] = (rows, nb.index, nb.mask)
        return self._eval[name]

    @property
    def eval_rows(self) -> torch.Tensor:
        return self.split_neighbors(self.eval_split)[0]

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

    def _collate_eval(self, positions: list[int]) -> dict:
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
            share if len(share) < len(rows) else _Positions(len(rows)),
            batch_size=self.batch_size,
            shuffle=False,
            collate_fn=self._eval_collate(name),
            num_workers=self.num_workers,
        )

    def val_dataloader(self) -> DataLoader:
        return self._eval_loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader(self.eval_split)

    def measured_spacing(self) -> float | None:
        """Median nearest-neighbor distance (m) among the measured training positions of each scene (the
        density of the survey the methods see; all training positions when no fraction is set), the median
        over scenes; None when a scene has fewer than two."""
        out = []
        for k in range(len(self.sets)):
            rows = self.measured_rows[self.row_scene[self.measured_rows] == k]
            if len(rows) < 2:
                return None
            d = torch.cdist(self.positions[rows].double(), self.positions[rows].double())
            d.fill_diagonal_(float("inf"))
            out.append(float(d.min(dim=1).values.median()))
        return float(np.median(out)) if out else None

    def split_summary(self) -> dict:
        """What results.json records about the splits."""
        return {
            "n_train": self.n_train,
            "n_fit": int(len(self.fit_rows)),
            "n_val": int(len(self.val_rows)),
            "n_test": int(len(self.test_rows)),
            "val_fraction": self.val_fraction,
            "val_seed": self.val_seed,
            "val_ids": [int(i) for i in self.ids[self.val_rows]],
            "measured_fraction": self.measured_fraction,
            "measured_seed": self.measured_seed,
            "n_measured": int(len(self.measured_rows)),
            # the survey's density: median distance from each measured position to its nearest other (m)
            "measured_spacing_m": self.measured_spacing(),
            "test_pool": self.test_pool,
            "measured_ids": (
                [int(i) for i in self.ids[self.measured_rows]]
                if self.measured_fraction is not None
                else "all training spectra"
            ),
        }

    def query_batches(self, positions, batch_size: int | None = None):
        """Batches for new transmitter positions ``[N, 3]`` of the (single) scene (no measured spectrum:
        ``tgt_spectrum`` is zeros), with neighbors from the training split as at test.  Used by graf-synthesize."""
        pos = torch.as_tensor(positions, dtype=torch.float64)
        pool = self._split("test")[1]
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
