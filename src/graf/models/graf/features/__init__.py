"""GRaF's neighbor-feature components: how the rays read the neighbors (``model/features=<mode>``).

- ``pooled`` (:class:`PooledFeatures`, the paper's): one token per neighbor spectrum;
- ``ray`` (:class:`RayFeatures`): per-ray tokens from each neighbor's feature map and pixel values at the
  ray's own direction;
- ``ray_knn`` (:class:`RayKNNFeatures`): ``ray`` plus a per-ray convex combination of the neighbors' values
  (IDW KNN at initialisation), corrected by the ray tracer;
- ``ray_weights`` (:class:`RayWeightsFeatures`): the output is only that per-ray convex combination, its
  weights corrected by the tokens and the ray tracer's state.

Each is configured by ``conf/model/features/<mode>.yaml`` (``_target_`` plus its own settings) and built by
:func:`build_features`; the interface is :class:`NeighborFeatures`.
"""

from graf.models.graf.features.base import (
    MODES,
    PAPER_MODE,
    Dims,
    NeighborFeatures,
    build_features,
    features_config,
)
from graf.models.graf.features.pooled import PooledFeatures
from graf.models.graf.features.ray import RayFeatures
from graf.models.graf.features.ray_knn import RayKNNFeatures
from graf.models.graf.features.ray_weights import RayWeightsFeatures

__all__ = [
    "MODES",
    "PAPER_MODE",
    "Dims",
    "NeighborFeatures",
    "PooledFeatures",
    "RayFeatures",
    "RayKNNFeatures",
    "RayWeightsFeatures",
    "build_features",
    "features_config",
]
