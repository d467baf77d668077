"""What every neighbor-feature component shares: the model sizes it is built from, its interface, and how a
config (``model/features=<mode>``: a dict with ``_target_``) becomes a component.

A component owns the parameters that differ between modes and the three steps of a ray that differ:

- :meth:`NeighborFeatures.prepare`: once per batch, what the rays will read (a per-batch context);
- :meth:`NeighborFeatures.scene_inputs`: for a group of rays, the voxel queries and the tokens they
  cross-attend to in the scene blocks, plus the per-ray state the last step needs;
- :meth:`NeighborFeatures.output`: the ray tracer's state, mean-pooled over the ray, -> ``(re, im)``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import ClassVar

import torch
from hydra.utils import get_class
from torch import nn

from graf.config_home import class_defaults
from graf.models.graf.buckets import static_shapes

# the paper's mode (supplement D): conf/model/graf.yaml's default (tests/models/test_graf_features.py checks it), and
# the mode of every checkpoint written before the modes existed (graf.models.graf.legacy)
PAPER_MODE = "pooled"
# mode name (model/features=<name>) -> component class
MODES = {
    "pooled": "graf.models.graf.features.PooledFeatures",
    "ray": "graf.models.graf.features.RayFeatures",
    "ray_knn": "graf.models.graf.features.RayKNNFeatures",
    "ray_weights": "graf.models.graf.features.RayWeightsFeatures",
}


@dataclass(frozen=True)
class Dims:
    """The sizes of the GRaF model a component is built into."""

    encoder_dim: int  # channels of the encoder's pooled vector and feature map
    position_dim: int  # PE width of an absolute position (3-D, or 4-D with the scene index)
    offset_dim: int  # PE width of a neighbor's offset from the target (3-D)
    mlp_dim: int  # hidden width of the model's MLPs
    d_model: int  # token / voxel latent width


def mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, d_out))


def complex_head(d_model: int, zero: bool) -> nn.Linear:
    """``Linear(d, 2)``: the ray's pooled state -> ``(re, im)``; zero at initialisation when the model starts
    as a KNN (``zero``: the prediction is then the KNN base alone)."""
    head = nn.Linear(d_model, 2)
    if zero:
        nn.init.zeros_(head.weight)
        nn.init.zeros_(head.bias)
    return head


class NeighborFeatures(nn.Module):
    """How the rays read the neighbors.  Subclasses set ``name`` (the mode), ``method_suffix`` (appended to the
    method name) and ``knn_based`` (the mode is itself a per-ray KNN: ``model.residual`` is refused).

    Args:
        dims: the model's sizes.
        residual: the model adds the KNN base to the real part (``model.residual``): the output head starts
            at zero, so the model starts as KNN.
        defer_output: leave the output's parameters to a later :meth:`make_output` call (the model's).
    """

    name: ClassVar[str] = ""
    method_suffix: ClassVar[str] = ""
    knn_based: ClassVar[bool] = False

    def __init__(self, dims: Dims, residual: bool = False, defer_output: bool = False):
        super().__init__()
        if residual and self.knn_based:
            raise ValueError(
                f"model/features={self.name} already adds its own per-ray KNN base: model.residual must be false"
            )
        self.dims, self.defer_output = dims, bool(defer_output)

    def make_output(self, dims: Dims, residual: bool) -> None:  # pragma: no cover - abstract
        """Build the output's parameters (:meth:`output`'s).  A subclass calls it at the end of its ``__init__``
        unless ``defer_output``: the GRaF model then calls it after its ray transformer, so that the random
        initialisation is drawn in the order of the model before the components (the same seed gives the same
        weights, and the main job the same figures, as before)."""
        raise NotImplementedError

    def prepare(self, model: nn.Module, batch: dict) -> dict:  # pragma: no cover - abstract
        """The batch's context for :meth:`scene_inputs` (``model``: the GRaF model, for its encoder and
        position encodings)."""
        raise NotImplementedError

    def scene_inputs(
        self, ctx: dict, q: torch.Tensor, bi: torch.Tensor, pix: torch.Tensor, one_item: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, dict]:  # pragma: no cover - abstract
        """``(queries, tokens, key mask, per-ray state)`` for the scene blocks, from the voxel queries ``q [n, S,
        d]`` of the rays at pixels ``pix [n]`` of items ``bi [n]`` (``one_item``: all of one item)."""
        raise NotImplementedError

    def output(self, state: torch.Tensor, ray: dict) -> torch.Tensor:  # pragma: no cover - abstract
        """The ray tracer's state mean-pooled over each ray ``[n, d]`` -> ``(re, im)`` ``[n, 2]``."""
        raise NotImplementedError


def neighbor_slots(
    model: nn.Module, mask: torch.Tensor, every_slot: Callable[[], torch.Tensor], real_slots: Callable[[], torch.Tensor]
) -> torch.Tensor:
    """What the encoder makes of each neighbor slot, ``[B, L, ...]``, zero for padded slots (``mask [B, L]``
    False).  With static shapes (:func:`graf.models.graf.buckets.static_shapes`: a GPU's default) ``every_slot()``
    encodes all ``B * L`` slots and the padded ones are zeroed, so that no count is read back to the host;
    otherwise ``real_slots()`` encodes only the real ones (``mask.sum()`` of them), scattered into place."""
    B, L = mask.shape
    if static_shapes(model, mask.device):
        out = every_slot()
        out = out.view(B, L, *out.shape[1:])
        return out.masked_fill(~mask.view(B, L, *[1] * (out.dim() - 2)), 0.0)
    real = real_slots()
    full = real.new_zeros(B, L, *real.shape[1:])
    full[mask] = real
    return full


def component_class(target: str) -> type[NeighborFeatures]:
    """The component class a config's ``_target_`` names (refused unless a :class:`NeighborFeatures`)."""
    try:
        cls = get_class(str(target))
    except Exception as exc:
        raise ValueError(f"model.features._target_={target!r} is not a class ({exc})") from None
    if not (isinstance(cls, type) and issubclass(cls, NeighborFeatures)):
        raise ValueError(f"model.features._target_={target!r} is not a NeighborFeatures component")
    return cls


def features_config(features: Mapping | str) -> dict:
    """A component config as a plain dict with ``_target_`` and every setting of the component, its defaults
    filled in (what the checkpoint records): ``features`` is such a mapping (Hydra's ``model/features`` node)
    or a mode name (its default settings)."""
    if isinstance(features, str):
        if features not in MODES:
            raise ValueError(f"model/features must be one of {tuple(MODES)}, got {features!r}")
        features = {"_target_": MODES[features]}
    if not isinstance(features, Mapping) or "_target_" not in features:
        raise ValueError(f"model.features must be a mode name or a config with _target_, got {features!r}")
    defaults = class_defaults(component_class(features["_target_"]), skip=("self", "dims", "residual", "defer_output"))
    return {
        "_target_": str(features["_target_"]),
        **defaults,
        **{str(k): v for k, v in features.items() if k != "_target_"},
    }


def build_features(config: dict, dims: Dims, residual: bool, defer_output: bool = False) -> NeighborFeatures:
    """The component of ``config`` (see :func:`features_config`) built for a model of sizes ``dims``."""
    settings = {k: v for k, v in config.items() if k != "_target_"}
    return component_class(config["_target_"])(dims, residual=residual, defer_output=defer_output, **settings)
