"""KNN-DL: neighbor spectra fused with per-pixel weights learned from geometry (see :mod:`.module`)."""

from graf.models.knn_dl.module import KNNDLModule
from graf.models.knn_dl.weightnet import WeightNet, upsample_maps

__all__ = ["KNNDLModule", "WeightNet", "upsample_maps"]
