"""KNN: a weighted mean of the L neighbors' spectra, with nothing to train (see :mod:`.module`)."""

from graf.models.knn.module import KNNModule
from graf.models.knn.weights import barycentric_weights, idw_weights

__all__ = ["KNNModule", "barycentric_weights", "idw_weights"]
