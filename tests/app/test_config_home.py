"""Each setting's default is stated in one place (graf.config_home): a class's home config file, or else its
constructor; every other config file states only what it changes.  Read from the files themselves (the defaults
lists followed by hand), so no composition can hide a restated value."""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from graf.config_home import CONF_DIR, defaults_from, home_values, is_wiring

HYDRA_KEYS = ("defaults",)


def _raw(path: Path) -> dict:
    return OmegaConf.to_container(OmegaConf.load(path), resolve=False) or {}


def _parents(path: Path, raw: dict) -> list[Path]:
    """The config files ``path`` extends: the plain entries of its defaults list (``- graf``,
    ``- base/tracing@_here_``), not the config groups it picks (``features: pooled``) nor ``_self_``."""
    out = []
    for entry in raw.get("defaults") or []:
        if isinstance(entry, str) and entry != "_self_" and not entry.startswith("/"):
            out.append(path.parent / f"{entry.split('@')[0]}.yaml")
    return out


def _effective(path: Path) -> dict:
    """``path``'s settings with those of the files it extends under them (the last wins, as Hydra merges)."""
    raw, out = _raw(path), {}
    for parent in _parents(path, raw):
        out.update(_effective(parent))
    out.update({k: v for k, v in raw.items() if k not in HYDRA_KEYS})
    return out


def _target(name: str):
    module, _, attr = name.rpartition(".")
    return getattr(importlib.import_module(module), attr)


def _python_defaults(obj) -> dict:
    params = inspect.signature(obj).parameters
    return {k: p.default for k, p in params.items() if p.default is not inspect.Parameter.empty}


def _same(a, b) -> bool:
    return (list(a) if isinstance(a, tuple) else a) == (list(b) if isinstance(b, tuple) else b)


def _restated(path: Path) -> list[str]:
    """The settings ``path`` states that it would have anyway: from a file it extends, from its class's home
    file, or from the constructor (a class of ours without a home file)."""
    raw = _raw(path)
    inherited = {}
    for parent in _parents(path, raw):
        inherited.update(_effective(parent))
    target = raw.get("_target_") or inherited.get("_target_")
    if not (isinstance(target, str) and target.startswith("graf.")):
        return []
    obj = _target(target)
    rel = path.relative_to(CONF_DIR).as_posix()
    home = getattr(obj, "config_home", None)
    base = home_values(home) if home and home != rel else {}
    base.update(_python_defaults(obj) if home is None else {})
    base.update({k: v for k, v in inherited.items() if not k.startswith("_")})
    return [
        f"{k}: {v!r}"
        for k, v in raw.items()
        if not k.startswith("_") and k not in HYDRA_KEYS and not is_wiring(v) and k in base and _same(base[k], v)
    ]


CONFIGS = sorted(p for p in CONF_DIR.rglob("*.yaml") if "hydra" not in p.relative_to(CONF_DIR).parts)


def test_no_config_file_restates_a_default_it_would_get_anyway():
    restated = {p.relative_to(CONF_DIR).as_posix(): r for p in CONFIGS if (r := _restated(p))}
    assert restated == {}, f"settings stated in two places (keep the home's; graf.config_home): {restated}"


@pytest.mark.parametrize(
    "target, home",
    [
        ("graf.models.graf.GRaFModule", "model/graf.yaml"),
        ("graf.models.knn.KNNModule", "model/knn.yaml"),
        ("graf.models.knn_dl.KNNDLModule", "model/knn_dl.yaml"),
        ("graf.models.nerf2.NeRF2Module", "model/nerf2.yaml"),
        ("graf.models.graf.features.RayFeatures", "model/features/ray.yaml"),
        ("graf.data.datamodule.SpectrumDataModule", "data/default.yaml"),
        ("graf.data.neighbors.NeighborSelector", "neighbors/random_3_10.yaml"),
        ("graf.data.scenes.NeRF2Scene", "scene_catalog/nerf2.yaml"),
        ("graf.sim.scene.SimulatedScene", "scene_catalog/base/tracing.yaml"),
    ],
)
def test_a_configured_class_states_no_default_of_its_home_file(target, home):
    obj = _target(target)
    assert obj.config_home == home
    twice = set(_python_defaults(obj)) & set(home_values(home))
    assert not twice, f"{target}: defaults in the constructor and in {home}: {sorted(twice)}"


def test_a_class_built_from_python_gets_the_home_files_values():
    from graf.models.graf import GRaFModule
    from graf.models.knn_dl import KNNDLModule

    graf = GRaFModule(d_model=8)
    home = home_values("model/graf.yaml")
    assert graf.hparams.d_model == 8 and graf.chunk_rays == home["chunk_rays"]  # 1024, where a constructor said 4096
    assert {k: graf.hparams[k] for k in home if k != "d_model"} == {k: v for k, v in home.items() if k != "d_model"}
    with pytest.raises(ValueError, match="max_rank=null"):  # the home's null: the run's L, filled in by a run only
        KNNDLModule()
    assert KNNDLModule(max_rank=4).hparams.lr == home_values("model/knn_dl.yaml")["lr"]


def test_a_second_home_or_an_unknown_setting_is_refused_at_import():
    class TwoHomes:
        def __init__(self, *, weighting: str = "idw", power: float, ridge: float):
            pass

    with pytest.raises(TypeError, match="both in the constructor and in model/knn.yaml"):
        defaults_from("model/knn.yaml")(TwoHomes)

    class Fewer:
        def __init__(self, *, weighting: str):
            pass

    with pytest.raises(TypeError, match="takes no setting"):
        defaults_from("model/knn.yaml")(Fewer)


def test_how_many_spectra_are_tested_has_one_setting():
    """``data.test_subset`` (N per scene; seed null: the first N of the split); ``trainer.limit_test_batches``, a
    second way to say it that also cut validation, is refused in one line naming the first."""
    import numpy as np

    from graf.app.config import check_run_settings
    from graf.data.scene_rows import seeded_subset
    from graf.errors import ConfigError

    test = np.arange(10, 20)
    assert seeded_subset(test, 3, None, "s").tolist() == [10, 11, 12]
    assert seeded_subset(test, 3, 0, "s").tolist() == seeded_subset(test, 3, 0, "s").tolist() != [10, 11, 12]
    check_run_settings(OmegaConf.create({"trainer": {"limit_test_batches": 1.0}}))
    with pytest.raises(ConfigError, match=r"trainer.limit_test_batches=8: .* data.test_subset=N"):
        check_run_settings(OmegaConf.create({"trainer": {"limit_test_batches": 8}}))
