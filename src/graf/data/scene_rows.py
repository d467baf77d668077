"""The scenes of a datamodule in memory: one table of rows, the splits as row sets, neighbors in row terms.

Every scene's spectra are concatenated into one tensor; a *row* is a spectrum's place in it, and ``row_scene``
says whose it is.  The splits (:mod:`graf.data.splits`) are sets of rows, and per-scene tables (gateway pose,
wavelength, ray length, bounds, scene index) are gathered per batch item through its scene.

:class:`SceneRows` is the part of :class:`graf.data.datamodule.SpectrumDataModule` that holds them: it loads the
scenes (:meth:`load_scenes`), selects neighbors among rows, each target's from its own scene only
(:meth:`select`), names each evaluation split's targets and neighbor pool (:meth:`split_rows`), checks at
set-up that every target a stage will select has a neighbor (:meth:`check_neighbors`), and summarises the
splits for results.json.  It reads the datamodule's settings (``scenes``, ``bands``, ``neighbors``,
``data_root``, the fractions and seeds, ``eval_split``, ``scene_index``).
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Sequence

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from graf.data.fingerprint import scene_fingerprint
from graf.data.neighbors import Neighbors, NoNeighborsError
from graf.data.spectrum_set import DataFormatError, SpectrumSet
from graf.data.splits import EVAL_SPLITS, carve_validation, measured_part

log = logging.getLogger(__name__)

ROW_SPLITS = ("train", "measured", "fit", "val", "test")
# every split whose targets a training run selects (training targets, then validation and test at its end)
ALL_SPLITS = ("train", "val", "test")


def scene_geometry(d: SpectrumSet) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """``(gateway position [3], rotation local -> world [3, 3], bounds [2, 3], ray length)`` of a scene (float64);
    the ray length is the farthest corner of its bounds from the gateway (m)."""
    p = torch.as_tensor(d.gateway_position, dtype=torch.float64)
    b = torch.as_tensor(d.bounds(), dtype=torch.float64)
    corners = torch.stack([torch.stack([b[i, 0], b[j, 1], b[m, 2]]) for i in (0, 1) for j in (0, 1) for m in (0, 1)])
    rot = torch.as_tensor(Rotation.from_quat(d.gateway_orientation).as_matrix())
    return p, rot, b, float((corners - p).norm(dim=1).max())


def seeded_subset(test: np.ndarray, size: int | None, seed: int | None, scene: str) -> np.ndarray:
    """At most ``size`` of a scene's test rows ``test``, drawn by ``seed`` alone (NumPy's PCG64 from ``[seed,
    crc32(scene)]``: the same subset whatever else a run sets), in their original order; the first ``size`` of
    them for ``seed`` None; all of them for ``size`` None or at least ``len(test)``."""
    if size is None or size >= len(test):
        return test
    if seed is None:
        return test[: int(size)]
    rng = np.random.default_rng([int(seed), zlib.crc32(scene.encode())])
    return test[np.sort(rng.choice(len(test), size=int(size), replace=False))]


def merge_neighbors(parts: list[tuple[torch.Tensor, Neighbors]], T: int, dtype: torch.dtype) -> Neighbors:
    """One :class:`Neighbors` for ``T`` targets from per-scene selections ``(target positions, neighbors)``,
    padded to the longest list."""
    Lmax = max(nb.index.shape[1] for _, nb in parts)
    out = Neighbors(
        index=torch.zeros(T, Lmax, dtype=torch.long),
        mask=torch.zeros(T, Lmax, dtype=torch.bool),
        distance=torch.zeros(T, Lmax, dtype=dtype),
        widened=torch.zeros(T, dtype=torch.bool),
        short=torch.zeros(T, dtype=torch.bool),
    )
    for t, nb in parts:
        w = nb.index.shape[1]
        out.index[t, :w], out.mask[t, :w], out.distance[t, :w] = nb.index, nb.mask, nb.distance
        out.widened[t], out.short[t] = nb.widened, nb.short
    return out


class SceneRows:
    """The scenes' rows, splits and per-scene tables (see the module docstring)."""

    # ------------------------------------------------------------------ loading
    def load_scenes(self) -> None:
        """Load every scene (ray-traced first when ``simulate_missing`` and its dataset file is missing) and build
        the rows, splits and per-scene tables."""
        if self.simulate_missing:
            for s, b in zip(self.scenes, self.bands):
                if hasattr(s, "ensure_dataset"):
                    s.ensure_dataset(self.data_root, b)
        self.sets = [s.load(self.data_root, b) for s, b in zip(self.scenes, self.bands)]
        splits = {name: [] for name in ROW_SPLITS}
        offset = 0
        for k, (d, band) in enumerate(zip(self.sets, self.bands)):
            for name, rows in self.scene_splits(k, d, band, offset).items():
                splits[name].append(rows)
            offset += len(d.ids)
        self.spectra = self.sets[0].spectra if len(self.sets) == 1 else torch.cat([d.spectra for d in self.sets])
        self.positions = torch.as_tensor(np.concatenate([np.asarray(d.positions, np.float64) for d in self.sets]))
        self.ids = torch.as_tensor(np.concatenate([np.asarray(d.ids, np.int64) for d in self.sets]))
        self.row_scene = torch.as_tensor(
            np.concatenate([np.full(len(d.ids), k, np.int64) for k, d in enumerate(self.sets)])
        )
        self.train_rows, self.measured_rows, self.fit_rows, self.val_rows, self.test_rows = (
            torch.as_tensor(np.concatenate(splits[s])) for s in ROW_SPLITS
        )
        # per-scene tables, gathered per batch item through its scene index
        gw_pos, gw_rot, bounds, ray_len = zip(*(scene_geometry(d) for d in self.sets))
        self.gw_pos = torch.stack(gw_pos).float()
        self.gw_rot = torch.stack(gw_rot).float()
        self.wavelength = torch.as_tensor([b.wavelength for b in self.bands], dtype=torch.float32)
        self.ray_length = torch.as_tensor(ray_len, dtype=torch.float32)
        self.bounds = torch.stack(bounds).float()
        self.checked_splits: set[str] = set()

    def scene_splits(self, k: int, d: SpectrumSet, band, offset: int) -> dict[str, np.ndarray]:
        """Scene ``k``'s rows of each split (its rows start at ``offset``), logged."""
        train = np.asarray(d.train_idx, np.int64) + offset
        measured = measured_part(train, self.measured_fraction, self.measured_seed, d.source)
        fit, val = carve_validation(measured, self.val_fraction, self.val_seed, d.source)
        test = seeded_subset(np.asarray(d.test_idx, np.int64), self.test_subset, self.test_subset_seed, d.name) + offset
        log.info(
            "scene %s (index %d): %d train (%s%d fit + %d validation) / %d test spectra%s (%s), band %s (%.4f m)",
            d.name,
            int(self.scene_index[k]),
            d.n_train,
            "" if len(measured) == len(train) else f"{len(measured)} measured: ",
            len(fit),
            len(val),
            d.n_test,
            "" if len(test) == d.n_test else f", {len(test)} of them tested (data.test_subset)",
            d.split_source,
            band.name,
            band.wavelength,
        )
        return {"train": train, "measured": measured, "fit": fit, "val": val, "test": test}

    # ------------------------------------------------------------------ neighbors
    def stage_splits(self, stage: str | None) -> tuple[str, ...]:
        """The splits whose targets ``setup(stage)`` checks for neighbors: those the stage will select.  A training
        run (``fit``, or no stage) uses every one (it validates and tests when it ends: all are checked before it
        starts); an evaluation (``test``: graf-eval, a zero-shot test, a test scene) validates, then tests the
        evaluated split (:func:`graf.run.evaluation.evaluate_model`), never the training targets; ``validate``
        the validation split; ``predict`` (graf-synthesize: new positions, neighbors from the test pool) none."""
        return {"validate": ("val",), "test": ("val", self.eval_split), "predict": ()}.get(stage, ALL_SPLITS)

    def check_neighbors(self, splits: Sequence[str] = ALL_SPLITS) -> None:
        """Every target of ``splits`` (names of :data:`EVAL_SPLITS`) has at least one neighbor under the run's
        selector (``exclude_within`` drops the nearest ones): checked once per split, at set-up, so a setting that
        leaves a target with none is one clear error before the stage starts, not a failure deep inside a
        loader."""
        for name in splits:
            if name in self.checked_splits:
                continue
            rows, pool = self.split_rows(name)
            for s in range(0, len(rows), 1024):
                self.select(rows[s : s + 1024], pool, train=False, quiet=True)
            self.checked_splits.add(name)

    def split_rows(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """``(target rows, neighbor pool)`` of an evaluation split (one of :data:`EVAL_SPLITS`)."""
        if name not in EVAL_SPLITS:
            raise ValueError(f"unknown split {name!r}: one of {', '.join(EVAL_SPLITS)}")
        pool = self.measured_rows if self.test_pool == "measured" else self.train_rows
        return {
            "test": (self.test_rows, pool),
            "val": (self.val_rows, self.fit_rows),
            "train": (self.fit_rows, self.fit_rows),
        }[name]

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
        return merge_neighbors(parts, len(rows), self.positions.dtype)

    # ------------------------------------------------------------------ scenes
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

    # ------------------------------------------------------------------ summaries
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
            "test_subset": self.test_subset,
            "test_subset_seed": self.test_subset_seed,
            "test_ids": [int(i) for i in self.ids[self.test_rows]],
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
