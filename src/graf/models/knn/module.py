"""KNN: a weighted mean of the L neighbors' spectra, with nothing to train.

``weighting: idw`` uses inverse-distance weights 1/d^power; ``weighting: barycentric`` uses the convex
weights of the interpolation theorem (supplement A, see :func:`barycentric_weights`).
"""

from __future__ import annotations

import torch

from graf.config_home import defaults_from
from graf.models.base import SpectrumModule
from graf.models.knn.weights import barycentric_weights, idw_weights

WEIGHTINGS = ("idw", "barycentric")


@defaults_from("model/knn.yaml")
class KNNModule(SpectrumModule):
    """KNN (the paper's non-learned baseline): the target's spectrum as a convex combination of its L nearest known
    transmitters' spectra.  Nothing is trained.

    Args (their defaults in ``conf/model/knn.yaml``, the one place they are stated: :mod:`graf.config_home`):
        weighting: ``idw`` (inverse-distance weights 1/d^power, method ``knn``) or ``barycentric`` (the convex weights
            of the interpolation theorem, the paper's supplement A.1: :func:`barycentric_weights`, ``knn-barycentric``).
        power: the inverse distance's exponent (idw).
        ridge: the weight of the distance penalty in the barycentric least squares.
    """

    def __init__(self, *, weighting: str, power: float, ridge: float):
        super().__init__()
        if weighting not in WEIGHTINGS:
            raise ValueError(f"model.weighting must be one of {WEIGHTINGS}, got {weighting!r}")
        self.save_hyperparameters()
        self.weighting, self.power, self.ridge = weighting, float(power), float(ridge)

    @property
    def method(self) -> str:
        return "knn" if self.weighting == "idw" else f"knn-{self.weighting}"

    def weights(self, batch: dict) -> torch.Tensor:
        """``[B, L]`` convex weights of the neighbors."""
        if self.weighting == "idw":
            return idw_weights(batch["tgt_pos"], batch["src_pos"], batch["src_mask"], power=self.power)
        return barycentric_weights(batch["tgt_pos"], batch["src_pos"], batch["src_mask"], ridge=self.ridge)

    def predict_spectra(self, batch: dict) -> torch.Tensor:
        w = self.weights(batch).to(batch["src_spectra"].dtype)
        return torch.einsum("bl,blhw->bhw", w, batch["src_spectra"])
