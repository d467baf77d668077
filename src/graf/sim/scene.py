"""Simulated scenes (``conf/scene/<name>.yaml`` with ``_target_: graf.sim.scene.SimulatedScene``).

The config models only what the scene needs: its geometry (a room or open ground, and box objects with
ITU materials), the gateway's pose, the region and count of transmitter positions, the array (element
pattern, pitch) and the tracing settings.  ``graf-simulate`` turns it into a dataset file per band
(:mod:`graf.sim.dataset`); ``load`` reads that file for training and evaluation, after comparing the settings
it records with the scene's (:mod:`graf.sim.checks`): a file made by other settings is refused.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np
import torch

from graf.bands import Band
from graf.config_home import defaults_from
from graf.data.spectrum_set import DataFormatError, SpectrumSet
from graf.geometry.shapes import SceneGeometry, build_geometry, sample_positions
from graf.sim.array import PATTERNS, Bartlett, array_positions, rotation_from_axes
from graf.sim.checks import compare_config
from graf.sim.dataset import generate, read_dataset, scene_config
from graf.sim.tracer import SionnaTracer, spectra_from_paths

log = logging.getLogger(__name__)


@defaults_from("scene_catalog/base/tracing.yaml")
class SimulatedScene:
    """Args:
    name: scene name (also the dataset folder under ``<data_root>/sim``).
    room / ground: the enclosure (see :func:`graf.geometry.shapes.build_geometry`).
    objects: name -> {material, center, size, yaw, thickness}; null removes an inherited object.
    gateway: {position, normal (the array faces it), x_axis (azimuth 0)}.
    transmitters: {count, min, max, clearance, seed, train_fraction, split_seed}.
    array: {rows, cols, pitch_wavelengths, pattern (iso | front | cos), hemisphere}.
    tracing: Sionna RT PathSolver settings (max_depth, refraction, diffraction, samples_per_src, ...)
        plus sources_per_call.
    description: free text for people.
    num_tx: read the limited dataset ``<band>-n<num_tx>.h5`` (made by ``graf-simulate sim.num_tx=N``)
        instead of the full one; never chosen silently.
    """

    kind = "simulated"

    def __init__(
        self,
        name: str,
        gateway: dict,
        transmitters: dict,
        tracing: dict,
        array: dict,
        room: dict | None = None,
        ground: dict | None = None,
        objects: dict | None = None,
        *,
        description: str,
        num_tx: int | None = None,
        band: str | None,
        fixed_band: bool,
        validation_only: bool = False,
    ):
        self.name = name
        # a validation layout: validated on, never tested (graf.run.build refuses it as a test scene); it does not
        # shape the dataset, so it is not in config()
        self.validation_only = bool(validation_only)
        self.band, self.fixed_band = (
            band,
            bool(fixed_band),
        )  # the run's band choice (graf.app.config.scene_band_config)
        self.num_tx = None if num_tx is None else int(num_tx)
        self.room, self.ground, self.objects = room, ground, objects or {}
        self.gateway, self.transmitters = dict(gateway), dict(transmitters)
        self.tracing, self.array = dict(tracing), dict(array)
        self.description = description
        if self.array.get("pattern", "cos") not in PATTERNS:
            raise ValueError(
                f"scene {name}: array.pattern must be one of {PATTERNS}, got {self.array.get('pattern')!r}"
            )
        self.geometry: SceneGeometry = build_geometry(room, ground, self.objects)
        self.rotation = rotation_from_axes(gateway["normal"], gateway["x_axis"])

    # ------------------------------------------------------------------ generating config
    def config(self) -> dict:
        """The full generating configuration (written into the dataset)."""
        return copy.deepcopy(
            {
                "name": self.name,
                "room": self.room,
                "ground": self.ground,
                "objects": {k: v for k, v in self.objects.items() if v is not None},
                "gateway": self.gateway,
                "transmitters": self.transmitters,
                "tracing": self.tracing,
                "array": self.array,
                "description": self.description,
            }
        )

    def positions(self, limit: int | None = None) -> np.ndarray:
        t = self.transmitters
        pos = sample_positions(
            self.geometry, int(t["count"]), t["min"], t["max"], int(t.get("seed", 0)), float(t.get("clearance", 0.05))
        )
        return pos if limit is None else pos[: int(limit)]

    def split(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Seeded train/test split of rows 0..n-1 (``transmitters.train_fraction``, ``split_seed``)."""
        frac = float(self.transmitters.get("train_fraction", 0.8))
        perm = np.random.default_rng(int(self.transmitters.get("split_seed", 0))).permutation(n)
        n_train = min(max(int(round(n * frac)), 1), n - 1)
        return np.sort(perm[:n_train]), np.sort(perm[n_train:])

    # ------------------------------------------------------------------ tracing
    def antenna_positions(self, band: Band) -> np.ndarray:
        a = self.array
        return array_positions(
            band.wavelength, int(a.get("rows", 4)), int(a.get("cols", 4)), float(a.get("pitch_wavelengths", 0.5))
        )

    def bartlett(self, band: Band, device="cpu"):
        """The array's Bartlett beamformer at ``band``."""
        return Bartlett(self.antenna_positions(band), band.wavelength, device=device)

    def tracer(self, band: Band, **tracing_overrides):
        """A Sionna RT tracer of this scene at ``band`` (tracing settings from the config, overridable)."""
        tracing = {**self.tracing, **tracing_overrides}
        return SionnaTracer(
            self.geometry,
            band.frequency_hz,
            self.gateway["position"],
            self.rotation,
            tracing,
            int(tracing.get("sources_per_call", 256)),
        )

    def spectra(self, tracer, bartlett, positions):
        """Trace ``positions``; returns (channels [n, K], float spectra [n, 90, 360], paths per position [n])."""
        gains, dirs, counts = tracer.trace(np.asarray(positions, float))
        h, s = spectra_from_paths(bartlett, gains, dirs, self.array.get("pattern", "cos"))
        return h, s, counts

    # ------------------------------------------------------------------ dataset files
    def dataset_path(self, data_root: str | Path, band: Band, num_tx: int | None = None) -> Path:
        suffix = "" if num_tx is None else f"-n{int(num_tx)}"
        return Path(data_root) / "sim" / self.name / f"{band.name}{suffix}.h5"

    def ensure_dataset(self, data_root: str | Path | None, band: Band) -> Path:
        """Ray-trace this scene's dataset at ``band`` (``num_tx`` positions) unless its file is there (studies
        set ``data.simulate_missing=true``); resumable as ``graf-simulate`` is."""
        if data_root is None:
            raise DataFormatError("data_root", "simulated scenes are read from data_root; set data_root=DIR")
        path = self.dataset_path(data_root, band, self.num_tx)
        if not path.is_file():
            log.info("simulating %s at %s (%s positions) into %s", self.name, band.name, self.num_tx or "all", path)
            generate(
                self,
                band,
                data_root,
                num_tx=self.num_tx,
                progress=False,
                device="cuda" if torch.cuda.is_available() else "cpu",
            )
        return path

    def load(self, data_root: str | Path | None, band: Band, num_tx: int | None = None) -> SpectrumSet:
        if data_root is None:
            raise DataFormatError("data_root", "simulated scenes are read from data_root; set data_root=DIR")
        num_tx = self.num_tx if num_tx is None else num_tx
        path = self.dataset_path(data_root, band, num_tx)
        if not path.is_file():
            # a limited run (sim.num_tx=N) is used only when asked for (scene.<name>.num_tx=N), never silently
            limited = sorted(path.parent.glob(f"{band.name}-n*.h5")) if num_tx is None else []
            found = [int(p.stem.rsplit("-n", 1)[1]) for p in limited if p.stem.rsplit("-n", 1)[1].isdigit()]
            raise DataFormatError(
                path,
                f"no dataset for scene {self.name} at band {band.name}; make it with "
                f"`graf-simulate scene={self.name} band={band.name} data_root={data_root}`"
                + (
                    f", or use a limited one that is there with scene.{self.name}.num_tx=N (N in {found})"
                    if found
                    else ""
                ),
            )
        data = read_dataset(path, name=self.name)
        count = int(self.transmitters["count"])
        n = count if num_tx is None else min(int(num_tx), count)  # len(self.positions(num_tx)), without sampling
        limit = "" if num_tx is None else f" sim.num_tx={num_tx}"
        compare_config(
            path,
            data.meta["config"],
            scene_config(self, band, n),
            self.name,
            f"it is not this scene's dataset: make one with `graf-simulate scene={self.name} band={band.name}{limit}` "
            "and the asked settings into another data_root (or replace this file with sim.overwrite=true), or ask "
            "for the settings it was made with",
        )
        return data
