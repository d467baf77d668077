"""Frequency bands (``conf/band``): everything wavelength-derived follows from ``frequency_hz``."""

from __future__ import annotations

SPEED_OF_LIGHT = 299_792_458.0


class Band:
    """A band (a plain class, not a dataclass: Hydra would turn a dataclass argument back into a config)."""

    def __init__(self, name: str, frequency_hz: float):
        frequency_hz = float(frequency_hz)
        if not frequency_hz > 0:
            raise ValueError(f"band {name!r}: frequency_hz must be > 0, got {frequency_hz}")
        self.name, self.frequency_hz = str(name), frequency_hz

    def __repr__(self) -> str:
        return f"Band(name={self.name!r}, frequency_hz={self.frequency_hz:g})"

    def __eq__(self, other) -> bool:
        return isinstance(other, Band) and (self.name, self.frequency_hz) == (other.name, other.frequency_hz)

    def __hash__(self) -> int:
        return hash((self.name, self.frequency_hz))

    @property
    def wavelength(self) -> float:
        """Wavelength in metres (also GRaF's voxel size)."""
        return SPEED_OF_LIGHT / self.frequency_hz
