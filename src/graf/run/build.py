"""Building a run from its config: bands, scenes, the neighbor selector and the datamodule that joins them, the
test scenes' datamodules (with their scene indices, seen or unseen), the model, loggers, callbacks and trainer.

Every object comes from its config node by ``_target_`` (Hydra's ``instantiate``); trainer callbacks, the
Optuna pruning one included, come from the ``callbacks`` group.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from graf.app.config import (
    check_run_settings,
    hz,
    load_band_config,
    run_settings,
    scene_band_config,
)
from graf.app.spec import RunSpec, as_spec
from graf.console import is_terminal
from graf.data.datamodule import SpectrumDataModule
from graf.data.fingerprint import describe, differences, eval_scene_index, find_scene, next_index, register_scene
from graf.data.neighbors import NeighborSelector
from graf.errors import ConfigError
from graf.models.base import checkpoint_class, read_checkpoint

log = logging.getLogger("graf")


def build_datamodule(run: RunSpec | DictConfig, which: str = "scene", scene_indices=None):
    """Bands, scenes, neighbor selector and the datamodule that joins them (``cfg.data``), for the run's scenes
    (``which="scene"``: what is trained on; ``"eval_scene"``: what is tested).  The fine-tuning settings
    (``cfg.finetune``: measured fraction, its seed, the test neighbor pool) apply to the scenes trained on."""
    spec = as_spec(run)
    cfg = spec.cfg
    configs = spec.scenes if which == "scene" else spec.eval_scenes
    if not configs:
        raise ConfigError(f"{which}= selects no scene")
    band_cfgs = [scene_band_config(c, spec.band) for c in configs]
    bands = [hydra.utils.instantiate(b) for b in band_cfgs]
    scenes = [hydra.utils.instantiate(c) for c in configs]
    neighbors = hydra.utils.instantiate(spec.neighbors)
    ft = cfg.get("finetune") or {}
    measured = (
        {
            "measured_fraction": ft.get("fraction"),
            "measured_seed": int(ft.get("seed") or 0),
            "test_pool": ft.get("test_pool") or "measured",
        }
        if which == "scene"
        else {}
    )
    make = hydra.utils.instantiate(cfg.data, _partial_=True)  # lists of objects must not pass through OmegaConf
    datamodule = make(
        scene=scenes,
        band=bands,
        neighbors=neighbors,
        data_root=cfg.get("data_root"),
        scene_indices=scene_indices,
        **measured,
    )
    return bands, scenes, neighbors, datamodule


def checkpoint_scenes(cfg: DictConfig) -> tuple[str | None, dict]:
    """``(path, {scene name: {"index", "band_hz"}})`` of the checkpoint a run starts from or tests
    (``finetune.init_from``, else ``ckpt_path``): the scenes it was trained on (empty for a checkpoint written
    before checkpoints recorded them, or when there is none)."""
    path = (cfg.get("finetune") or {}).get("init_from") or cfg.get("ckpt_path")
    if not path:
        return None, {}
    ckpt = read_checkpoint(path)
    return str(path), dict((ckpt.get("graf") or {}).get("scenes") or {})


def check_bands(cfg: DictConfig, trained: dict, dm, source: str) -> None:
    """Refuse a scene at a band the model was not trained at (``trained``: name -> {"band_hz"}) unless
    ``cross_band=true``: the seed trains one model per band (E.5), so a cross-band run is a transfer study,
    not an accident."""
    if not trained or cfg.get("cross_band"):
        return
    bands = {round(float(v["band_hz"])) for v in trained.values() if v.get("band_hz")}
    for d, b in zip(dm.sets, dm.bands):
        if bands and round(float(b.frequency_hz)) not in bands:
            raise ConfigError(
                f"{source} was trained at {', '.join(hz(x) for x in sorted(bands))} (scenes "
                f"{', '.join(sorted(trained))}), but scene {d.name} is at {hz(b.frequency_hz)} in this run: a "
                "cross-band transfer.  Set cross_band=true to run it anyway (the bands and unseen_layouts studies "
                "do), or band=... to match"
            )


@dataclass(eq=False)
class EvalScene:
    """A scene the final evaluations test: its name, datamodule, and whether the model was trained on it."""

    eval_scene: str
    datamodule: SpectrumDataModule
    within_scene: bool


@dataclass(eq=False)
class BuiltRun:
    """What :func:`build` makes of a config.  ``cfg`` is the config that runs: the one given with the model
    settings taken from the run filled in (:func:`run_model_config`); it is the one results.json records."""

    cfg: DictConfig
    neighbors: NeighborSelector
    datamodule: SpectrumDataModule
    evaluations: list[EvalScene]
    model: L.LightningModule
    loggers: list
    trainer: L.Trainer
    output_dir: Path
    scene_table: dict


def run_model_config(cfg: DictConfig, neighbors: NeighborSelector) -> DictConfig:
    """The config with the model settings that follow from the run filled in, for the model and every baseline
    (:func:`model_config_for_neighbors`)."""
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.model = model_config_for_neighbors(cfg.model, neighbors, "model")
        for name, node in (cfg.get("baselines") or {}).items():
            if isinstance(node, DictConfig):
                cfg.baselines[name] = model_config_for_neighbors(node, neighbors, f"baselines.{name}")
    return cfg


def model_config_for_neighbors(node: DictConfig, neighbors: NeighborSelector, where: str = "model") -> DictConfig:
    """A model config with ``max_rank: null`` (KNN-DL's scale of its rank and neighbor-count features) set to the
    largest L the neighbor selector gives (``neighbors.max_L``): the one place that decides it."""
    if "max_rank" not in node or node.max_rank is not None:
        return node
    node = node.copy()
    node.max_rank = int(neighbors.max_L)
    log.info("%s.max_rank=%d: the largest L of the run's neighbor selector", where, neighbors.max_L)
    return node


def build(run: RunSpec | DictConfig, trains: bool = True) -> BuiltRun:
    """Instantiate band, scene, neighbor selector, datamodule (set up), model, loggers and trainer of a run
    (a :class:`~graf.app.spec.RunSpec`; a composed config is read into one).  ``trains``: whether the run trains the
    model on its scenes (graf-eval and a zero-shot test do not: a test scene is then "within-scene" only when the
    checkpoint was trained on its content)."""
    spec = as_spec(run)
    cfg = spec.cfg
    check_run_settings(cfg)
    check_not_validation_only(cfg, spec.tested_scenes)
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg.torch_threads))
    if cfg.get("seed") is not None:
        L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out = spec.output_dir
    out.mkdir(parents=True, exist_ok=True)
    source, known = checkpoint_scenes(cfg)
    _, _, neighbors, datamodule = build_datamodule(spec)
    cfg = run_model_config(cfg, neighbors)
    datamodule.setup("fit" if trains else "test")  # checks the neighbors of the targets the run will select
    check_bands(cfg, known, datamodule, source)  # fine-tuning or testing a checkpoint at another band: a transfer
    # a scene the checkpoint was trained on (the same content, whatever its name) keeps its index; a scene this
    # run trains on gets the next; the table is what the checkpoints this run writes record.  A run that trains
    # nothing gives its scenes the index of a test scene (eval_scene_index: an unseen one the one fixed index)
    table = dict(known)
    if trains or not known:
        datamodule.set_scene_indices(
            [
                table[register_scene(table, d.name, fp, next_index(table))]["index"]
                for d, fp in zip(datamodule.sets, datamodule.fingerprints())
            ]
        )
    else:
        given = [eval_scene_index(table, d.name, fp) for d, fp in zip(datamodule.sets, datamodule.fingerprints())]
        datamodule.set_scene_indices([k for k, _ in given])
        datamodule.scene_index_source = given[0][1]
    seen = table if trains or not known else known
    evaluations = eval_datamodules(spec, datamodule, table, seen=seen)
    check_per_scene(cfg, datamodule, evaluations, trains, seen)
    for ev in evaluations:
        if ev.datamodule is not datamodule:
            check_bands(cfg, table, ev.datamodule, source or "the model")
    if cfg.get("seed") is not None:
        # the initial weights depend on the seed alone, not on how much set-up drew from the global generators
        # before (each test scene's set-up draws: a job tested on six scenes got other weights than one tested on
        # one, with the same config, seed and threads)
        L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    model = hydra.utils.instantiate(cfg.model)
    model.scene_table = dict(table)  # what the checkpoints it writes record: the checkpoint's and this run's scenes
    model.run_settings = run_settings(cfg)
    loggers, callbacks = instantiate_group(cfg, "logger"), instantiate_group(cfg, "callbacks")
    trainer = hydra.utils.instantiate(trainer_args(cfg), logger=loggers or False, callbacks=callbacks)
    return BuiltRun(cfg, neighbors, datamodule, evaluations, model, loggers, trainer, out, table)


def instantiate_group(cfg: DictConfig, group: str) -> list:
    """The objects of a config group's entries (loggers, callbacks), composed by Hydra; an entry may make nothing
    (None: the Optuna pruning callback of a run that is no search trial)."""
    made = (
        hydra.utils.instantiate(c)
        for c in (cfg.get(group) or {}).values()
        if isinstance(c, DictConfig) and "_target_" in c
    )
    return [x for x in made if x is not None]


def check_not_validation_only(cfg: DictConfig, configs: list) -> None:
    """Refuse to test on a validation layout (``validation_only: true`` in its catalog entry: ``conference_v4``,
    ``office_v4``): it validates and draws learning curves (``test=false``) so that no choice sees a study's test
    layouts, and is never itself a test scene."""
    if not cfg.get("test", True):
        return
    for c in configs:
        if c.get("validation_only"):
            name = c.get("name")
            raise ConfigError(
                f"scene {name} is a validation layout (validation_only: true in scene_catalog/{name}.yaml): it is "
                "validated on, never tested; validate on it with test=false (as graf-curves does), or test on "
                "another scene"
            )


def check_per_scene(cfg: DictConfig, datamodule, evaluations: list, trains: bool, seen: dict | None = None) -> None:
    """Refuse, in one line, a run that trains a per-scene method (its class says ``per_scene = True``: RF Gaussian
    splatting, whose Gaussians live in one scene's frame) on several scenes, or tests it on a scene it was not
    trained on (a zero-shot test); a scene of the name of one it was trained on (``seen``: the model's scenes by
    content) but other data (another NeRF2 folder) is named with both folders and content fingerprints.  The class
    is the checkpoint's when the run tests one without training (graf-eval ``ckpt_path``, ``finetune=none``).
    Fine-tuning it on a new scene trains it there, and is allowed."""
    path = (cfg.get("finetune") or {}).get("init_from") or cfg.get("ckpt_path")
    saved = (read_checkpoint(path).get("graf") or {}).get("target") if path and not trains else None
    target = str(saved or (cfg.get("model") or {}).get("_target_") or "")
    try:  # a class that cannot be imported (or, a checkpoint's, is refused) is reported where the model is made
        cls = checkpoint_class(saved, path) if saved is not None else hydra.utils.get_class(target)
        per_scene = bool(target) and getattr(cls, "per_scene", False)
    except Exception:
        return
    if not per_scene:
        return
    method = target.rsplit(".", 1)[-1]
    names = [d.name for d in datamodule.sets]
    if trains and len(names) > 1:
        raise ConfigError(f"{method} is a per-scene method: train it on one scene, not on {', '.join(names)}")
    unseen = [ev.eval_scene for ev in evaluations if not ev.within_scene]
    for ev in (ev for ev in evaluations if not ev.within_scene):
        same = [v for k, v in (seen or {}).items() if k.split("#")[0] == ev.eval_scene and v.get("fingerprint")]
        if same:  # trained on a scene of this name, but other data: say which, and what differs
            here, theirs = ev.datamodule.fingerprints()[0], same[0]["fingerprint"]
            raise ConfigError(
                f"{method} is a per-scene method, and the {ev.eval_scene} given here is not the {ev.eval_scene} it "
                f"was trained on ({differences(theirs, here)}): here {describe(here)}, trained on {describe(theirs)}; "
                "test it on the data it was trained on, or train it on this (finetune=... finetune.init_from=CKPT "
                "fine-tunes it)"
            )
    if unseen:
        raise ConfigError(
            f"{method} is a per-scene method and was not trained on {', '.join(unseen)}: it cannot be tested there "
            "zero-shot; test it on the scene it was trained on (eval_scene=same), or train it there (finetune=... "
            "finetune.init_from=CKPT fine-tunes it)"
        )


def eval_datamodules(spec: RunSpec, train_dm, table: dict | None = None, seen: dict | None = None) -> list[EvalScene]:
    """What the final evaluations test (:class:`EvalScene`).  Without
    ``eval_scene`` (``eval_scene=same``) and ``eval_band`` the training datamodule itself (within-scene).
    Otherwise one datamodule per test scene (``eval_scene=same`` with an ``eval_band``: the training scenes at
    that band), its targets from that scene's splits and their neighbors from that scene's training split
    (all of it: the measured fraction of a fine-tuning run applies to the scenes it trains on).  ``table``:
    the scenes the model knows (name -> {"index"}; default: the training datamodule's), so a test scene the
    model was trained on keeps its scene index and is reported as within-scene, and an unseen one gets the one
    fixed index of unseen scenes (:func:`graf.data.fingerprint.eval_scene_index`).  ``seen``: the scenes the model
    was trained on, by content (default: ``table``); a run that trains nothing (graf-eval of a checkpoint) passes
    the checkpoint's alone."""
    configs = spec.eval_scenes
    eval_band = spec.eval_band
    if not configs and not eval_band:
        within = seen is None or all(
            find_scene(seen, d.name, fp) is not None for d, fp in zip(train_dm.sets, train_dm.fingerprints())
        )
        return [EvalScene(train_dm.scene_name, train_dm, within)]
    if not configs:
        configs = spec.scenes
    band = load_band_config(eval_band) if eval_band else spec.band
    if table is None:
        table = {}
        for d, fp, k in zip(train_dm.sets, train_dm.fingerprints(), train_dm.scene_index.tolist()):
            register_scene(table, d.name, fp, k)
    names = [str(c.get("name")) for c in configs]
    out = []
    for c, name in zip(configs, names):
        scene = OmegaConf.create({name: OmegaConf.to_container(c, resolve=True)})  # resolved in the run's config
        sub = OmegaConf.create(
            {
                key: OmegaConf.to_container(v, resolve=True) if isinstance(v, DictConfig) else v
                for key, v in (
                    ("eval_scene", scene),
                    ("band", band),
                    ("neighbors", spec.neighbors),
                    ("data", spec.cfg.data),
                    ("data_root", spec.cfg.get("data_root")),
                )
            }
        )
        _, _, _, dm = build_datamodule(sub, "eval_scene")
        dm.setup("test")
        fp = dm.fingerprints()[0]
        key = find_scene(table, name, fp)  # by content: another folder of the same name is unseen
        within = key is not None and (seen is None or find_scene(seen, name, fp) is not None)
        k, how = eval_scene_index(table, name, fp)  # never by its place in the list
        dm.set_scene_indices([k])
        dm.scene_index_source = how
        log.info(
            "test scene %s at %s: %s (scene index %d: %s)",
            name,
            dm.bands[0].name,
            "within-scene (the model was trained on it)" if within else "unseen in training (zero-shot)",
            k,
            how,
        )
        out.append(EvalScene(name, dm, within))
    return out


def trainer_args(cfg: DictConfig) -> DictConfig:
    """``cfg.trainer`` without the keys that are not Trainer arguments, after applying them:
    ``float32_matmul_precision`` (``highest`` | ``high`` = TF32 on NVIDIA GPUs | ``medium``; null: torch's)."""
    t = OmegaConf.to_container(cfg.trainer, resolve=True)
    fmp = t.pop("float32_matmul_precision", None)
    if fmp:
        torch.set_float32_matmul_precision(str(fmp))
    return OmegaConf.create(t)


def evaluation_trainer(cfg: DictConfig, loggers=(), callbacks=()) -> L.Trainer:
    """The trainer of the final evaluations (validation and test of the final weights): each evaluates its whole
    split (how many test spectra: ``data.test_subset``); validation during training (off by default) is the fit
    trainer's business.  Their bars are drawn on a terminal only: elsewhere the table that ends the command says
    what they found."""
    t = trainer_args(cfg)
    return L.Trainer(
        accelerator=t.get("accelerator", "auto"),
        devices=t.get("devices", 1),
        num_nodes=t.get("num_nodes", 1),
        strategy=t.get("strategy", "auto"),  # under DDP each rank evaluates its share of the positions
        use_distributed_sampler=False,  # graf deals the positions itself (no padded duplicates)
        precision=t.get("precision", "32-true"),
        logger=list(loggers) or False,
        callbacks=list(callbacks),
        enable_progress_bar=bool(t.get("enable_progress_bar", True)) and is_terminal(),
        enable_model_summary=False,
        enable_checkpointing=False,
        default_root_dir=t.get("default_root_dir"),
    )
