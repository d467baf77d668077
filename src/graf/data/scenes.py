"""Scenes (``conf/scene``): where a scene's measurements come from, and how they are loaded.

A scene object is built by Hydra from its config and turned into a :class:`SpectrumSet` by
:meth:`load`, given the run's ``data_root`` and band.
"""

from __future__ import annotations

from pathlib import Path

from graf.bands import Band
from graf.data.nerf2_format import read_nerf2_folder
from graf.data.spectrum_set import DataFormatError, SpectrumSet

EMBEDDED_PREFIX = "embedded:"
EMBEDDED_DIR = Path(__file__).resolve().parent.parent / "embedded"


def resolve_scene_path(path: str, data_root: str | Path | None) -> Path:
    """``embedded:NAME`` is a folder shipped inside the package; an absolute path is used as is; a
    relative path is looked up under ``data_root`` first, then the working directory."""
    if path is None or str(path) in ("", "???"):
        raise DataFormatError("scene.path", "no scene folder given: set scene.<name>.path=DIR (scene=nerf2 scene.nerf2.path=DIR)")
    path = str(path)
    if path.startswith(EMBEDDED_PREFIX):
        p = EMBEDDED_DIR / path[len(EMBEDDED_PREFIX):]
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


class NeRF2Scene:
    """A scene stored in NeRF2's spatial-spectrum folder format (real measurements, or a user's own).

    Args:
        name: scene name written into results.
        path: the folder (``embedded:rfid_s23_200`` for the shipped slice).
        split_seed / train_fraction: used only when the folder has no index files.
        band / fixed_band: the band name a run uses for this scene (fixed: whatever the run's band= says, as
            for measured data); read by the run, see :func:`graf.cli.common.scene_band_config`.
    """

    kind = "nerf2_folder"

    def __init__(self, name: str, path: str, split_seed: int = 0, train_fraction: float = 0.8,
                 band: str | None = None, fixed_band: bool = False):
        self.name, self.path, self.band, self.fixed_band = name, path, band, bool(fixed_band)
        self.split_seed, self.train_fraction = split_seed, train_fraction

    def load(self, data_root: str | Path | None, band: Band) -> SpectrumSet:
        folder = resolve_scene_path(self.path, data_root)
        return read_nerf2_folder(folder, name=self.name, frequency_hz=band.frequency_hz,
                                 split_seed=self.split_seed, train_fraction=self.train_fraction)
