from graf.models.knn.module import KNNModule
from graf.models.knn.weights import barycentric_weights, idw_weights

__all__ = ["KNNModule", "barycentric_weights", "idw_weights"]
