"""What every method, the simulator and the data readers share, depending on nothing above it (torch and
numpy only): the spectrum grid and its ray directions (:mod:`.grid`), rays and the voxels sampled along them
(:mod:`.rays`), and positional encodings and coordinate frames (:mod:`.encoding`)."""

from graf.geometry.grid import (
    N_AZIMUTH,
    N_ELEVATION,
    N_RAYS,
    SPECTRUM_SHAPE,
    directions,
    grid_directions,
    local_directions,
)

__all__ = ["N_AZIMUTH", "N_ELEVATION", "N_RAYS", "SPECTRUM_SHAPE", "directions", "grid_directions", "local_directions"]
