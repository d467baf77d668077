"""NeRF2: the per-scene RF radiance field baseline (see :mod:`.module`)."""

from graf.models.nerf2.module import NeRF2Module
from graf.models.nerf2.network import NeRF2Encoding, NeRF2Network
from graf.models.nerf2.renderer import render_rays, sample_distances

__all__ = ["NeRF2Module", "NeRF2Network", "NeRF2Encoding", "render_rays", "sample_distances"]
