"""Scenes (``conf/scene``): where a scene's measurements come from, and how they are loaded.

A scene object is built by Hydra from its config and turned into a :class:`SpectrumSet` by
:meth:`load`, given the run's ``data_root`` and band.
"""

from __future__ import annotations

from pathlib import Path

from graf.bands import Band
from graf.config_home import defaults_from
from graf.data.nerf2_format import POSITION_ROWS_RULES, read_nerf2_folder
from graf.data.spectrum_set import DataFormatError, SpectrumSet
from graf.errors import ConfigError

EMBEDDED_PREFIX = "embedded:"
EMBEDDED_DIR = Path(__file__).resolve().parent.parent / "embedded"


def resolve_scene_path(path: str, data_root: str | Path | None) -> Path:
    """``embedded:NAME`` is a folder shipped inside the package; an absolute path is used as is; a
    relative path is looked up under ``data_root`` first, then the working directory."""
    if path is None or str(path) in ("", "???"):
        raise DataFormatError(
            "scene.path", "no scene folder given: set scene.<name>.path=DIR (scene=nerf2 scene.nerf2.path=DIR)"
        )
    path = str(path)
    if path.startswith(EMBEDDED_PREFIX):
        p = EMBEDDED_DIR / path[len(EMBEDDED_PREFIX) :]
        if not p.is_dir():
            known = sorted(d.name for d in EMBEDDED_DIR.iterdir() if d.is_dir())
            raise DataFormatError(p, f"unknown embedded scene {path!r}; embedded: {known}")
        return p
    p = Path(path).expanduser()
    if p.is_absolute():
        return p
    if data_root is not None and (Path(data_root) / p).exists():
        return Path(data_root) / p
    return p


@defaults_from("scene_catalog/nerf2.yaml")
class NeRF2Scene:
    """A scene stored in NeRF2's spatial-spectrum folder format (real measurements, or a user's own).

    Args:
        name: scene name written into results.
        path: the folder (``embedded:rfid_s23_200`` for the shipped slice).
        split_seed / train_fraction: used only when the folder has no index files.
        position_rows: ``"exact"`` (tx_pos.csv has one row per spectrum id 1..largest id, NeRF2's rule) or
            ``"at_least"`` (a slice whose tx_pos.csv holds a larger dataset's rows: more rows are accepted with a
            warning); see :func:`graf.data.nerf2_format.read_nerf2_folder`.
        band / fixed_band: the band name a run uses for this scene (fixed: whatever the run's band= says, as
            for measured data); read by the run, see :func:`graf.app.config.scene_band_config`.
    """

    kind = "nerf2_folder"

    def __init__(
        self,
        name: str,
        path: str,
        *,
        split_seed: int,
        train_fraction: float,
        band: str | None,
        fixed_band: bool,
        position_rows: str,
    ):
        if (
            isinstance(train_fraction, bool)
            or not isinstance(train_fraction, (int, float))
            or not 0.0 < float(train_fraction) < 1.0
        ):
            raise ConfigError(
                f"scene.{name}.train_fraction must be in (0, 1) (the seeded split's training part when "
                f"the folder has no index files), got {train_fraction!r}"
            )
        if isinstance(split_seed, bool) or not isinstance(split_seed, int):
            raise ConfigError(f"scene.{name}.split_seed must be an integer, got {split_seed!r}")
        if position_rows not in POSITION_ROWS_RULES:
            raise ConfigError(
                f"scene.{name}.position_rows must be 'exact' (tx_pos.csv rows = the largest spectrum id) "
                f"or 'at_least' (more rows accepted, with a warning), got {position_rows!r}"
            )
        self.name, self.path, self.band, self.fixed_band = name, path, band, bool(fixed_band)
        self.split_seed, self.train_fraction = split_seed, float(train_fraction)
        self.position_rows = position_rows

    def load(self, data_root: str | Path | None, band: Band) -> SpectrumSet:
        folder = resolve_scene_path(self.path, data_root)
        return read_nerf2_folder(
            folder,
            name=self.name,
            frequency_hz=band.frequency_hz,
            split_seed=self.split_seed,
            train_fraction=self.train_fraction,
            position_rows=self.position_rows,
        )
