"""GRaF's hyperparameters checked once, when the model is built: a value out of range is refused with a
message naming the setting (``model.<name>``)."""

from __future__ import annotations

from collections.abc import Mapping

from graf.app.config import check_bool, check_int
from graf.models.graf.features.residual import WEIGHTINGS
from graf.models.schedule import check_rates

LOSSES = ("mse", "log_mse")
ATTENTION_KERNELS = ("auto", "sdpa", "math")


def check_settings(hp: Mapping) -> None:
    """Refuse a GRaFModule hyperparameter (``hp``: the constructor's arguments) out of its range."""
    if hp["weighting"] not in WEIGHTINGS:
        raise ValueError(f"model.weighting must be one of {WEIGHTINGS}, got {hp['weighting']!r}")
    if hp["loss"] not in LOSSES:
        raise ValueError(f"model.loss must be one of {LOSSES}, got {hp['loss']!r}")
    sizes = ("d_model", "scene_blocks", "ray_heads", "ray_head_dim", "max_samples", "rays_per_step", "chunk_rays")
    if min(hp[k] for k in sizes) < 1:
        raise ValueError("GRaF sizes must be positive")
    if hp["d_model"] % 2:
        raise ValueError(
            f"model.d_model must be even (the voxel distance encoding is sin/cos pairs), got {hp['d_model']}"
        )
    if not hp["length_unit"] > 0:
        raise ValueError(f"model.length_unit must be > 0 (metres), got {hp['length_unit']}")
    if not hp["voxel_wavelengths"] > 0:
        raise ValueError(f"model.voxel_wavelengths must be > 0, got {hp['voxel_wavelengths']}")
    if hp["ray_window"] < 0:
        raise ValueError(f"model.ray_window must be >= 0 (0: attention over the whole ray), got {hp['ray_window']}")
    if hp["attention"] not in ATTENTION_KERNELS:
        raise ValueError(f"model.attention must be one of {ATTENTION_KERNELS}, got {hp['attention']!r}")
    check_rates(hp["lr"], hp["lr_decay"])
    for key in ("fast_inference", "fast_training"):  # checked, not cast: a string "no" is no true
        check_bool(hp[key], f"model.{key}")
    check_int(hp["train_pieces"], "model.train_pieces", low=1, none=True)  # null: torch's threads
