"""Checkpoints written before the neighbor-feature components (``model/features``) still load and predict the
same.  They recorded the mode as the string hyperparameter ``neighbor_features`` (earlier ``neighbour_features``)
beside ``ray_feature_dim`` and ``pixel_window``, and kept the mode's parameters at the top of the state dict
(``mlp1.*``, ``ray_proj.*``, ``ray_tokens.*``, ``head.*``, ``weight_query.*``), the output head after every
other parameter.  Here the old hyperparameters become the component's config (with a FutureWarning), the old
keys move under ``features.``, and an old optimiser state is put in the new order of the parameters."""

from __future__ import annotations

import warnings
from collections.abc import Mapping

from torch import nn

from graf.models.graf.features import MODES, PAPER_MODE, features_config

MODE_KEYS = ("neighbor_features", "neighbour_features")  # the old string hyperparameter, both spellings
SETTING_KEYS = ("ray_feature_dim", "pixel_window")  # the ray modes' settings, then top-level hyperparameters
LEGACY_KEYS = (*MODE_KEYS, *SETTING_KEYS)
INPUT_PREFIXES = ("mlp1.", "ray_proj.", "ray_tokens.")  # registered right after the encoder, as now
OUTPUT_PREFIXES = ("head.", "weight_query.")  # registered last, after the ray blocks
COMPONENT = "features."


def upgrade_arguments(features: Mapping | str, legacy: Mapping) -> dict:
    """The component config of GRaFModule's ``features`` argument and its deprecated keyword arguments
    ``legacy`` (those of :data:`LEGACY_KEYS`; any other is refused)."""
    unknown = sorted(set(legacy) - set(LEGACY_KEYS))
    if unknown:
        raise TypeError(f"GRaFModule got unexpected keyword argument(s): {', '.join(unknown)}")
    if not legacy:
        return features_config(features)
    mode = next((legacy[k] for k in MODE_KEYS if k in legacy), None)
    warnings.warn(
        f"GRaF hyperparameter(s) {', '.join(sorted(legacy))} are deprecated (a checkpoint written before "
        f"model/features, or an old override): use model/features={mode or '<mode>'} and "
        "model.features.<setting>",
        FutureWarning,
        stacklevel=3,
    )
    if mode is not None and features != PAPER_MODE:
        raise ValueError(f"give model/features or the deprecated neighbor_features={mode}, not both")
    config = features_config(features if mode is None else str(mode))
    if config["_target_"] != MODES[PAPER_MODE]:  # a pooled checkpoint recorded the (unused) ray settings too
        config.update({k: legacy[k] for k in SETTING_KEYS if k in legacy})
    return config


def upgrade_hparams(hparams: Mapping) -> dict:
    """A checkpoint's hyperparameters in the current form (unchanged when they already are)."""
    hp = {k: v for k, v in hparams.items() if k not in LEGACY_KEYS}
    legacy = {k: v for k, v in hparams.items() if k in LEGACY_KEYS}
    if legacy:
        hp["features"] = upgrade_arguments(hparams.get("features", PAPER_MODE), legacy)
    return hp


def is_legacy_key(name: str) -> bool:
    return name.startswith(INPUT_PREFIXES + OUTPUT_PREFIXES)


def upgrade_state_dict(module, state_dict: dict, prefix: str, *args) -> None:
    """Load pre-hook (``register_load_state_dict_pre_hook``): the old keys of the mode's parameters move under
    ``features.`` (in place, so that strict loading matches)."""
    for key in [k for k in state_dict if k.startswith(prefix) and is_legacy_key(k[len(prefix) :])]:
        state_dict[prefix + COMPONENT + key[len(prefix) :]] = state_dict.pop(key)


def upgrade_optimizer_states(model: nn.Module, checkpoint: dict) -> None:
    """An old checkpoint's optimiser states (one group of all parameters, in the old order: the output head
    last) put in the order of ``model.parameters()``, so that a resumed run keeps each parameter's moments."""
    if not any(is_legacy_key(k) for k in checkpoint.get("state_dict", {})):
        return
    names = [n for n, _ in model.named_parameters()]
    output = [n for n in names if n.startswith(COMPONENT) and n[len(COMPONENT) :].startswith(OUTPUT_PREFIXES)]
    old_order = [n for n in names if n not in output] + output
    new_index = {i: names.index(n) for i, n in enumerate(old_order)}
    for state in checkpoint.get("optimizer_states") or []:
        groups = state.get("param_groups") or []
        if len(groups) != 1 or list(groups[0]["params"]) != list(range(len(names))):
            raise ValueError(
                "an old GRaF checkpoint's optimiser state is not the one group of every parameter that GRaF's "
                "optimiser has: it cannot be resumed (start from its weights with finetune.init_from=)"
            )
        state["state"] = {new_index[int(i)]: s for i, s in state["state"].items()}


# what each GRaF checkpoint layout changed (GRaFModule.LAYOUT_CHANGES)
LAYOUT_CHANGES = {
    2: "positions are now metres in the gateway frame (layout 1 normalised them by each scene's "
    "box), ray directions are encoded, and voxels are encoded by their distance in wavelengths "
    "(layout 1 had a learned voxel-index table sized by max_samples)",
    3: "each ray's voxels now run from its own entry to its own exit of the scene box (layout 2 "
    "cut every ray at the box's farthest corner), so the same weights see other voxels",
}
