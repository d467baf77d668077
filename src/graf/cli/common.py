"""What graf-train and graf-eval share: building the run from the config, validating and testing the
final weights, and writing results.

Every command writes ``results.json`` into its Hydra output folder::

    {"method", "scene", "band_hz", "n_train", "n_test",
     "metrics": {"val/mse", ..., "test/mse", "test/psnr", "test/ssim", "test/lpips"}, "seconds", "config",
     "splits", "ray_sampling", ...}

and, with ``save_predictions=true``, ``predictions.npz`` (``pred``, ``target``: float32 [N, 90, 360] in
[0, 1]; ``ids``: int [N]).  A figure of predicted vs true spectra (``spectra.png``) goes beside them.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import platform
import sys
import time
from pathlib import Path

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

import graf
from graf.callbacks import PredictionCollector
from graf.data.fingerprint import find_scene, next_index, register_scene
from graf.errors import ConfigError, UserError  # ConfigError: re-exported for the commands
from graf.io import atomic_write_json, atomic_write_npz
from graf.plotting import plot_spectra_grid

log = logging.getLogger("graf")

# The configs ship inside the package (src/graf/conf; conf/ in the checkout links to it).  Every
# @hydra.main reads them as a package resource, so an installed wheel works from any folder; add a
# folder of your own with Hydra's --config-dir.  CONF_DIR is the same folder on disk (for tests).
CONF_PATH = "pkg://graf.conf"
CONF_DIR = Path(graf.__file__).resolve().parent / "conf"


def task_wrapper(task):
    """Run a task; on failure log the exception (and the output folder) before re-raising; always close
    the loggers (wandb included), so a failed run in a sweep leaves a finished, inspectable record."""

    @functools.wraps(task)
    def wrapped(cfg: DictConfig, *args, **kwargs):
        try:
            return task(cfg, *args, **kwargs)
        except Exception as exc:
            if (is_user_error(exc) or hasattr(exc, "exit_code")) and os.environ.get("HYDRA_FULL_ERROR") != "1":
                log.error("%s failed: %s (output folder: %s)", cfg.get("task_name", "task"), user_message(exc),
                          _output_dir(cfg))
            else:
                log.exception("%s failed; output folder: %s", cfg.get("task_name", "task"), _output_dir(cfg))
            raise
        finally:
            try:
                import wandb

                if wandb.run is not None:
                    wandb.finish()
            except ImportError:  # pragma: no cover
                pass

    return wrapped


def _output_dir(cfg: DictConfig) -> Path:
    try:
        return Path(cfg.paths.output_dir)
    except Exception:  # ${hydra:...} outside a Hydra app
        return Path.cwd()




def is_user_error(exc: BaseException) -> bool:
    """Errors in what the user gave (data, config values, checkpoints), whose message says what is wrong:
    :class:`graf.errors.UserError` (``ConfigError``, ``DataFormatError``, ``CheckpointError``,
    ``NoNeighborsError``), a mandatory config value left unset, and a constructor refusing a config value
    (Hydra's instantiation error)."""
    from hydra.errors import InstantiationException
    from omegaconf.errors import MissingMandatoryValue

    return isinstance(exc, (UserError, MissingMandatoryValue, InstantiationException))


def user_message(exc: BaseException) -> str:
    """A user error's message on one line: a constructor's own refusal rather than Hydra's three-line wrapper
    around it (``Error in call to target ...``), with the config node it came from."""
    from hydra.errors import InstantiationException

    cause = exc.__cause__ if isinstance(exc, InstantiationException) else None
    if cause is not None and str(cause):
        key = getattr(exc, "full_key", None)
        return f"{cause}" + (f" (in {key})" if key and str(key) not in str(cause) else "")
    return " ".join(str(exc).split("\n")) if "\n" in str(exc) else str(exc)


def cli_errors(main):
    """For a command's ``main`` (beneath ``@hydra.main``): a user error (:func:`is_user_error`) ends the command
    with its message alone on stderr and exit code 2, instead of a page of traceback; ``HYDRA_FULL_ERROR=1``
    shows the full traceback.  In a multirun the error is raised as usual, so the sweep records the failed
    job and goes on with the others."""

    @functools.wraps(main)
    def wrapped(cfg: DictConfig, *args, **kwargs):
        try:
            return main(cfg, *args, **kwargs)
        except Exception as exc:
            from hydra.core.hydra_config import HydraConfig
            from hydra.types import RunMode

            multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
            if hasattr(exc, "exit_code") and not multirun:  # a run stopped on purpose (pre-emption): its own code
                print(str(exc), file=sys.stderr)
                sys.exit(int(exc.exit_code))
            if not is_user_error(exc) or multirun or os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            print(f"error: {user_message(exc)}\n(HYDRA_FULL_ERROR=1 shows the full traceback)", file=sys.stderr)
            sys.exit(2)

    return wrapped


METRIC_NAMES = ("mse", "psnr", "ssim", "lpips")
# test/psnr_swapped: PSNR with every target's neighbours replaced by another target's; test/reliance_db: test/psnr
# minus it (how much a method reads its neighbours; None for a method that takes none)
EVAL_METRICS = tuple(f"{s}/{m}" for s in ("val", "test") for m in METRIC_NAMES) + tuple(
    f"{s}/{m}" for s in ("val", "test") for m in ("psnr_swapped", "reliance_db"))


def scene_configs(node) -> list[DictConfig]:
    """The scene configs a ``scene`` or ``eval_scene`` node selects, in order.  ``scene=conference_v1`` composes
    to ``scene.conference_v1: {...}`` and ``scene=[conference_v1,office_v1]`` to one entry per scene (Hydra's
    list selection; each option places ``scene_catalog/<name>`` under its own name); a flat config with a
    ``_target_`` (graf-bench's ``scenes.<key>``) is one scene."""
    if node is None:
        return []
    if isinstance(node, DictConfig) and "_target_" in node:
        return [node]
    return [v for v in node.values() if isinstance(v, DictConfig) and "_target_" in v]


def single_scene_config(cfg: DictConfig, command: str) -> DictConfig:
    """The one scene of a command that works on one scene (graf-simulate, graf-oracle, graf-synthesize)."""
    scenes = scene_configs(cfg.get("scene"))
    if len(scenes) != 1:
        raise ConfigError(f"{command} works on one scene; scene= selects {len(scenes)} "
                          f"({', '.join(str(s.get('name')) for s in scenes) or 'none'})")
    return scenes[0]


def band_choices() -> list[str]:
    """The options of the ``band`` config group."""
    return sorted(p.stem for p in (CONF_DIR / "band").glob("*.yaml"))


def load_band_config(name: str) -> DictConfig:
    path = CONF_DIR / "band" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"unknown band {name!r}: one of {', '.join(band_choices())}")
    return OmegaConf.load(path)


def scene_band_config(scene_cfg: DictConfig, run_band: DictConfig | None) -> DictConfig:
    """A scene's band: its own when fixed (measured data: rfid_s23 is 915 MHz whatever the run says), else the
    run's ``band=...``, else the scene's default (simulated scenes: 2.4 GHz, the paper's band)."""
    own = scene_cfg.get("band")
    if scene_cfg.get("fixed_band") and own:
        return load_band_config(own)
    if run_band is not None:
        return run_band
    if own:
        return load_band_config(own)
    raise ConfigError(f"scene {scene_cfg.get('name', '?')!r} does not say its carrier frequency: add "
                      f"band=<one of {', '.join(band_choices())}> (the band its spectra were measured at)")


def build_datamodule(cfg: DictConfig, which: str = "scene", scene_indices=None):
    """Bands, scenes, neighbour selector and the datamodule that joins them (``cfg.data``), for the scenes
    of ``cfg[which]`` (``scene``: what is trained on; ``eval_scene``: what is tested).  The fine-tuning settings (``cfg.finetune``: measured fraction,
    its seed, the test neighbour pool) apply to the scenes trained on."""
    configs = scene_configs(cfg.get(which))
    if not configs:
        raise ConfigError(f"{which}= selects no scene")
    band_cfgs = [scene_band_config(c, cfg.get("band")) for c in configs]
    bands = [hydra.utils.instantiate(b) for b in band_cfgs]
    scenes = [hydra.utils.instantiate(c) for c in configs]
    neighbors = hydra.utils.instantiate(cfg.neighbors)
    ft = cfg.get("finetune") or {}
    measured = {"measured_fraction": ft.get("fraction"), "measured_seed": int(ft.get("seed") or 0),
                "test_pool": ft.get("test_pool") or "measured"} if which == "scene" else {}
    make = hydra.utils.instantiate(cfg.data, _partial_=True)  # lists of objects must not pass through OmegaConf
    datamodule = make(scene=scenes, band=bands, neighbors=neighbors, data_root=cfg.get("data_root"),
                      scene_indices=scene_indices, **measured)
    return bands, scenes, neighbors, datamodule


def assign_scene_indices(known: dict[str, int], names: list[str]) -> list[int]:
    """The scene index of each scene in ``names``: its index in ``known`` (the scenes a model was trained on,
    name -> index) when there, else a new index after every known one (an unseen scene)."""
    out, new = [], (max(known.values()) + 1) if known else 0
    for n in names:
        if n in known:
            out.append(int(known[n]))
        else:
            out.append(new)
            new += 1
    return out


def eval_scene_indices(train_names: list[str], eval_names: list[str]) -> list[int]:
    """The scene index of each test scene: its training index when the model was trained on it, else a new
    index after the training scenes' (an unseen scene)."""
    return assign_scene_indices({n: i for i, n in enumerate(train_names)}, eval_names)


def checkpoint_scenes(cfg: DictConfig) -> tuple[str | None, dict]:
    """``(path, {scene name: {"index", "band_hz"}})`` of the checkpoint a run starts from or tests
    (``finetune.init_from``, else ``ckpt_path``): the scenes it was trained on (empty for a checkpoint written
    before checkpoints recorded them, or when there is none)."""
    from graf.models.base import read_checkpoint

    path = (cfg.get("finetune") or {}).get("init_from") or cfg.get("ckpt_path")
    if not path:
        return None, {}
    ckpt = read_checkpoint(path)
    return str(path), dict((ckpt.get("graf") or {}).get("scenes") or {})


def _hz(v: float) -> str:
    return f"{v / 1e9:.3g} GHz" if v >= 1e9 else f"{v / 1e6:.4g} MHz"


def family(scene: str) -> str:
    """A catalog scene's layout family: ``conference_v2`` -> ``conference`` (a scene without variants is its
    own family)."""
    return scene.rsplit("_v", 1)[0] if "_v" in scene and scene.rsplit("_v", 1)[1].isdigit() else scene


def heldout_scenes(train: list[str], heldout) -> list[str]:
    """``eval_scene=heldout``: the catalog scenes of the training scenes' families that the run does not train
    on (``heldout: auto``), or those of a list that share a family with a training scene."""
    families = {family(n) for n in train}
    if heldout == "auto":
        candidates = sorted(p.stem for p in (CONF_DIR / "scene_catalog").glob("*.yaml"))
    else:
        candidates = [str(n) for n in heldout]
        unknown = [n for n in candidates if not (CONF_DIR / "scene_catalog" / f"{n}.yaml").is_file()]
        if unknown:
            raise ConfigError(f"eval_scene.heldout: unknown scene(s) {', '.join(unknown)}")
    return [n for n in candidates if family(n) in families and n not in train]


def expand_heldout(cfg: DictConfig) -> DictConfig:
    """The run's config with ``eval_scene=heldout`` replaced by the held-out scenes' configs (composed from
    the catalog; their interpolations resolve in the run's config), or by nothing (a within-scene run) when
    no training scene has a held-out layout."""
    ev = cfg.get("eval_scene")
    if not isinstance(ev, DictConfig) or "heldout" not in ev:
        return cfg
    train = [str(c.get("name")) for c in scene_configs(cfg.get("scene"))]
    names = heldout_scenes(train, ev.heldout)
    cfg = cfg.copy()
    with open_dict(cfg):
        if not names:
            log.info("eval_scene=heldout: no held-out layout of %s: testing within-scene", ", ".join(train))
            cfg.eval_scene = None
            return cfg
        from hydra import compose

        composed = compose(config_name="train", overrides=[f"eval_scene=[{','.join(names)}]"])
        cfg.eval_scene = OmegaConf.create(OmegaConf.to_container(composed.eval_scene, resolve=False))
    log.info("eval_scene=heldout: testing on %s (held out from training on %s)", ", ".join(names), ", ".join(train))
    return cfg


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
                f"{source} was trained at {', '.join(_hz(x) for x in sorted(bands))} (scenes "
                f"{', '.join(sorted(trained))}), but scene {d.name} is at {_hz(b.frequency_hz)} in this run: a "
                "cross-band transfer.  Set cross_band=true to run it anyway (the bands and unseen_layouts studies "
                "do), or band=... to match")


def run_settings(cfg: DictConfig) -> dict:
    """The settings of a training run that its checkpoints record (``checkpoint["graf"]["run"]``: data,
    neighbours, seed, trainer), so that resuming with other ones is refused or recorded
    (:func:`graf.cli.train.check_resume`)."""
    c = OmegaConf.to_container(cfg, resolve=True)
    trainer = {k: v for k, v in (c.get("trainer") or {}).items() if k not in ("_target_", "default_root_dir")}
    return {"data": c.get("data"), "neighbors": c.get("neighbors"), "seed": c.get("seed"), "trainer": trainer}


def check_run_settings(cfg: DictConfig) -> None:
    """Top-level settings that must be integers, checked before anything is built (one clear error)."""
    for key, low in (("seed", None), ("torch_threads", 1)):
        v = cfg.get(key)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, int) or (low is not None and v < low):
            raise ConfigError(f"{key} must be an integer{'' if low is None else f' >= {low}'}, got {v!r}")


def build(cfg: DictConfig, trains: bool = True) -> dict:
    """Instantiate band, scene, neighbour selector, datamodule (set up), model, loggers and trainer.  ``trains``:
    whether the run trains the model on its scenes (graf-eval and a zero-shot test do not: a test scene is then
    "within-scene" only when the checkpoint was trained on its content)."""
    check_run_settings(cfg)
    if cfg.get("torch_threads"):
        torch.set_num_threads(int(cfg.torch_threads))
    if cfg.get("seed") is not None:
        L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out = _output_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    source, known = checkpoint_scenes(cfg)
    _, _, neighbors, datamodule = build_datamodule(cfg)
    datamodule.setup("fit")
    check_bands(cfg, known, datamodule, source)  # fine-tuning or testing a checkpoint at another band: a transfer
    # a scene the checkpoint was trained on (the same content, whatever its name) keeps its index; a new one
    # gets the next; the table is what the checkpoints this run writes record
    table = dict(known)
    datamodule.set_scene_indices([table[register_scene(table, d.name, fp, next_index(table))]["index"]
                                  for d, fp in zip(datamodule.sets, datamodule.fingerprints())])
    evaluations = eval_datamodules(cfg, datamodule, table, seen=table if trains or not known else known)
    for ev in evaluations:
        if ev["datamodule"] is not datamodule:
            check_bands(cfg, table, ev["datamodule"], source or "the model")
    model = hydra.utils.instantiate(cfg.model)
    model.scene_table = dict(table)  # what the checkpoints it writes record: the checkpoint's and this run's scenes
    model.run_settings = run_settings(cfg)
    loggers = [hydra.utils.instantiate(c) for c in (cfg.get("logger") or {}).values()
               if isinstance(c, DictConfig) and "_target_" in c]
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values()
                 if isinstance(c, DictConfig) and "_target_" in c]
    if cfg.get("optuna_trial"):  # a trial of the Optuna sweeper: report validation during training, prune
        from graf.sweeps.pruning import pruning_callback

        cb = pruning_callback(cfg.optuna_trial)
        if cb is not None:
            callbacks.append(cb)
    trainer = hydra.utils.instantiate(trainer_args(cfg), logger=loggers or False, callbacks=callbacks)
    return {"neighbors": neighbors, "datamodule": datamodule, "evaluations": evaluations, "model": model,
            "loggers": loggers, "trainer": trainer, "output_dir": out, "scene_table": table}


def eval_datamodules(cfg: DictConfig, train_dm, table: dict | None = None, seen: dict | None = None) -> list[dict]:
    """What the final evaluations test: ``[{"eval_scene", "datamodule", "within_scene"}]``.  Without
    ``eval_scene`` (``eval_scene=same``) and ``eval_band`` the training datamodule itself (within-scene).
    Otherwise one datamodule per test scene (``eval_scene=same`` with an ``eval_band``: the training scenes at
    that band), its targets from that scene's splits and their neighbours from that scene's training split
    (all of it: the measured fraction of a fine-tuning run applies to the scenes it trains on).  ``table``:
    the scenes the model knows (name -> {"index"}; default: the training datamodule's), so a test scene the
    model was trained on keeps its scene index and is reported as within-scene, and an unseen one gets a new
    index.  ``seen``: the scenes the model was trained on, by content (default: ``table``); a run that trains
    nothing (graf-eval of a checkpoint) passes the checkpoint's alone."""
    configs = scene_configs(cfg.get("eval_scene"))
    eval_band = cfg.get("eval_band")
    if not configs and not eval_band:
        within = seen is None or all(find_scene(seen, d.name, fp) is not None
                                     for d, fp in zip(train_dm.sets, train_dm.fingerprints()))
        return [{"eval_scene": train_dm.scene_name, "datamodule": train_dm, "within_scene": within}]
    if not configs:
        configs = scene_configs(cfg.get("scene"))
    band = load_band_config(str(eval_band)) if eval_band else cfg.get("band")
    if table is None:
        table = {}
        for d, fp, k in zip(train_dm.sets, train_dm.fingerprints(), train_dm.scene_index.tolist()):
            register_scene(table, d.name, fp, k)
    names = [str(c.get("name")) for c in configs]
    out, new = [], next_index(table)
    for c, name in zip(configs, names):
        scene = OmegaConf.create({name: OmegaConf.to_container(c, resolve=True)})  # resolved in the run's config
        sub = OmegaConf.create({key: OmegaConf.to_container(v, resolve=True) if isinstance(v, DictConfig) else v
                                for key, v in (("eval_scene", scene), ("band", band),
                                             ("neighbors", cfg.neighbors), ("data", cfg.data),
                                             ("data_root", cfg.get("data_root")))})
        _, _, _, dm = build_datamodule(sub, "eval_scene")
        dm.setup("test")
        key = find_scene(table, name, dm.fingerprints()[0])  # by content: another folder of the same name is unseen
        within = key is not None and (seen is None or find_scene(seen, name, dm.fingerprints()[0]) is not None)
        if key is not None:
            k = int(table[key]["index"])
        else:
            k, new = new, new + 1
        dm.set_scene_indices([k])
        log.info("test scene %s at %s: %s (scene index %d)", name, dm.bands[0].name,
                 "within-scene (the model was trained on it)" if within else "unseen in training (zero-shot)", k)
        out.append({"eval_scene": name, "datamodule": dm, "within_scene": within})
    return out


def ray_sampling(model, dm) -> dict | None:
    """Samples per ray and the effective voxel (sample spacing) of a ray-rendering model on each of the
    datamodule's scenes; logs a warning where ``max_samples`` caps S (voxels longer than nominal)."""
    out = {}
    for k, d in enumerate(dm.sets):
        geometry = {"ray_length": dm.ray_length[k:k + 1], "wavelength": dm.wavelength[k:k + 1],
                    "gw_pos": dm.gw_pos[k:k + 1], "gw_rot": dm.gw_rot[k:k + 1], "bounds": dm.bounds[k:k + 1],
                    "scene_index": dm.scene_index[k:k + 1]}
        r = model.ray_sampling(geometry)
        if r is None:
            return None
        out[d.name] = r
        if r["capped"]:
            log.warning("%s on %s: max_samples caps the samples per ray at %d (%d needed), so each sample spans "
                        "%.2f wavelengths (%.3f m) instead of %.2f", type(model).__name__, d.name,
                        r["samples_per_ray"], r["uncapped_samples"], r["sample_spacing_wavelengths"],
                        r["sample_spacing_m"], r["nominal_spacing_wavelengths"])
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
    """The trainer of the final evaluations (validation and test of the final weights).  Both evaluate
    ``trainer.limit_test_batches`` of their split; validation during training (off by default) is the fit
    trainer's business."""
    t = trainer_args(cfg)
    limit = t.get("limit_test_batches", 1.0)
    return L.Trainer(accelerator=t.get("accelerator", "auto"), devices=t.get("devices", 1),
                     precision=t.get("precision", "32-true"), logger=list(loggers) or False,
                     callbacks=list(callbacks), enable_progress_bar=bool(t.get("enable_progress_bar", True)),
                     enable_model_summary=False, enable_checkpointing=False, limit_val_batches=limit,
                     limit_test_batches=limit, default_root_dir=t.get("default_root_dir"))


def evaluate_model(cfg: DictConfig, model, dm, loggers=(), timing: dict | None = None) -> tuple[dict, dict]:
    """Validation then test metrics of ``model`` (``{val/..., test/...}``) and the test predictions; with
    ``timing`` (a dict), the wall seconds of each loop go into it (``val_s``, ``test_s``).  ``validate=false``
    (studies, which choose nothing) skips validation: the ``val/...`` figures are then None; ``test=false``
    (the trials of a hyperparameter search, which must not see the test split) skips the test: the
    ``test/...`` figures are then None."""
    collector = PredictionCollector()
    trainer = evaluation_trainer(cfg, loggers, [collector])
    t0 = time.perf_counter()
    metrics = {}
    if cfg.get("validate", True):
        trainer.validate(model=model, datamodule=dm, verbose=False)
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
    t1 = time.perf_counter()
    if cfg.get("test", True):
        trainer.test(model=model, datamodule=dm, verbose=False)
        metrics.update({k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")})
    t2 = time.perf_counter()
    if cfg.get("reliance", True) and getattr(model, "uses_neighbours", True):
        for split, done in (("val", cfg.get("validate", True)), ("test", cfg.get("test", True))):
            swapped = swapped_psnr(cfg, model, dm, split) if done else None
            if swapped is not None and metrics.get(f"{split}/psnr") is not None:
                metrics[f"{split}/psnr_swapped"] = swapped
                metrics[f"{split}/reliance_db"] = metrics[f"{split}/psnr"] - swapped
                for lg in trainer.loggers:  # beside the split's other figures (csv, wandb)
                    lg.log_metrics({f"{split}/psnr_swapped": swapped,
                                    f"{split}/reliance_db": metrics[f"{split}/reliance_db"]}, step=trainer.global_step)
                    lg.save()
    if timing is not None:
        timing.update(val_s=round(t1 - t0, 3), test_s=round(t2 - t1, 3), reliance_s=round(time.perf_counter() - t2, 3))
    return {k: metrics.get(k) for k in EVAL_METRICS}, collector.arrays()


def swapped_psnr(cfg: DictConfig, model, dm, split: str = "test") -> float | None:
    """Neighbour reliance's second pass: the ``split`` (test or val) PSNR with each target's neighbours replaced by another
    target's of the same scene (a derangement seeded by ``reliance_seed``; the same L, positions and spectra of
    real neighbours, only the wrong ones).  A model that reads its neighbours loses PSNR; one that ignores them
    scores the same.  None when a scene has a single target in the split."""
    seed = int(cfg.get("reliance_seed") or 0)
    if dm.swapped_neighbors(dm.eval_split if split == "test" else "val", seed) is None:
        return None
    trainer = evaluation_trainer(cfg)
    dm.swap_seed = seed
    try:
        (trainer.test if split == "test" else trainer.validate)(model=model, datamodule=dm, verbose=False)
    finally:
        dm.swap_seed = None
    return float(trainer.callback_metrics[f"{split}/psnr"])


def test_and_report(cfg: DictConfig, objects: dict, started: float, task: str) -> dict:
    """Validate and test the model, then write results.json (+ predictions.npz, spectra.png).  Returns the
    metrics (``val/...`` and ``test/...``)."""
    trainer, model, train_dm = objects["trainer"], objects["model"], objects["datamodule"]
    evaluations = objects.get("evaluations") or [{"eval_scene": train_dm.scene_name, "datamodule": train_dm,
                                                   "within_scene": True}]
    timing = dict(objects.get("timing") or {})
    done = []
    for ev in evaluations:  # each test scene on its own (the first one's figures are the run's headline)
        t = dict(timing)
        m, a = evaluate_model(cfg, model, ev["datamodule"], objects["loggers"] if not done else (), t)
        done.append((ev, m, a, t))
    (first, metrics, arrays, timing) = done[0]
    # every test scene's figures, for objectives over all of them (val/psnr@mean; graf.sweeps.objectives)
    objects["evaluation_metrics"] = [m for _, m, _, _ in done]
    dm = first["datamodule"]
    out: Path = objects["output_dir"]
    config = OmegaConf.to_container(cfg, resolve=True)
    if objects.get("checkpoint"):  # graf-eval of a checkpoint: the model that ran is the checkpoint's
        config["model"] = objects["checkpoint"]["model"]
    results = {
        "method": getattr(model, "method", type(model).__name__),
        "scene": dm.scene_name,
        "train_scenes": [d.name for d in train_dm.sets],
        "eval_scene": first["eval_scene"],
        "within_scene": bool(first["within_scene"]),
        "band_hz": float(dm.bands[0].frequency_hz),
        "train_bands_hz": [float(b.frequency_hz) for b in train_dm.bands],
        "n_train": dm.n_train,
        "n_test": int(len(arrays["ids"])),
        "metrics": metrics,
        "seconds": round(time.perf_counter() - started, 3),
        "config": config,
        "task": task,
        "eval_split": dm.eval_split,
        "split_source": "; ".join(d.split_source for d in dm.sets),
        "splits": dm.split_summary(),
        "neighbors": repr(objects["neighbors"]),
        "trainable_parameters": int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
        "global_step": int(objects.get("checkpoint", {}).get("global_step", trainer.global_step)),
        "device": str(model.device),
        "versions": {"graf": graf.__version__, "torch": torch.__version__, "python": platform.python_version()},
    }
    n_test = int(len(arrays["ids"]))
    if n_test:  # the whole test loop (prediction and the four metrics) per spectrum
        timing["test_s_per_spectrum"] = round(timing["test_s"] / n_test, 4)
    results["timing"] = timing
    sampling = ray_sampling(model, dm)
    if sampling is not None:
        results["ray_sampling"] = sampling
    if objects.get("checkpoint"):
        results["checkpoint"] = {k: v for k, v in objects["checkpoint"].items() if k != "model"}
    if cfg.get("save_predictions"):
        atomic_write_npz(out / "predictions.npz", **arrays)
        results["predictions"] = "predictions.npz"
    if int(cfg.get("plot_count", 0)) > 0 and len(arrays["ids"]):
        fig = plot_spectra_grid(arrays["pred"], arrays["target"], arrays["ids"], out / "spectra.png",
                                title=f"{results['method']} on {dm.scene_name}", max_rows=int(cfg.plot_count))
        results["figure"] = fig.name
        for lg in objects["loggers"]:
            if hasattr(lg, "log_image"):
                lg.log_image(key="test/spectra", images=[str(fig)])
    baselines = [(name, bcfg) for name, bcfg in selected_baselines(cfg).items() if bcfg != cfg.model]
    rows, per_eval = [], []
    for i, (ev, m, a, t) in enumerate(done):  # every test scene: the model, then its baselines on the same data
        head = results if i == 0 else {"method": results["method"], "scene": ev["eval_scene"],
                                       "n_test": int(len(a["ids"])), "metrics": m}
        brows = [_test_baseline(cfg, name, bcfg, ev["datamodule"]) for name, bcfg in baselines]
        if int(cfg.get("save_samples") or 0) > 0:
            for method, arr in [(results["method"], a)] + [(r["method"], r.pop("_arrays")) for r in brows]:
                save_samples(out, ev["eval_scene"], method, arr, int(cfg.save_samples))
        for r in brows:
            r.pop("_arrays", None)
        rows += [head, *brows]
        per_eval.append({r["method"]: {"metrics": r["metrics"], "seconds": r["seconds"],
                                       "trainable_parameters": r["trainable_parameters"]} for r in brows})
    if per_eval[0]:
        results["baselines"] = per_eval[0]
    if len(done) > 1 or not first["within_scene"] or first["eval_scene"] != train_dm.scene_name:
        results["evaluations"] = [
            {"eval_scene": ev["eval_scene"], "within_scene": bool(ev["within_scene"]), "metrics": m,
             "n_test": int(len(a["ids"])), "band_hz": float(ev["datamodule"].bands[0].frequency_hz),
             "scene_index": int(ev["datamodule"].scene_index[0]), "splits": ev["datamodule"].split_summary(),
             "timing": t, "baselines": b} for (ev, m, a, t), b in zip(done, per_eval)]
    if objects.get("training"):  # steps asked and reached, and why training stopped early if it did
        results["training"] = objects["training"]
    if objects.get("resumed"):  # the checkpoint resumed from, and the trainer settings changed since
        results["resumed"] = objects["resumed"]
    if objects.get("finetune"):
        results["finetune"] = objects["finetune"]
    if objects.get("scene_table"):
        results["scene_table"] = objects["scene_table"]
    if cfg.get("regime"):
        results["regime"] = str(cfg.regime)
    atomic_write_json(out / "results.json", results)
    log.info("results: %s", out / "results.json")
    print(format_metrics_table(rows))
    if "evaluations" in results:  # say which test scenes the model was trained on
        print("; ".join(f"{e['eval_scene']}: {'within-scene (trained on it)' if e['within_scene'] else 'zero-shot'}"
                        for e in results["evaluations"]))
    if cfg.get("regime"):
        print(f"regime: {cfg.regime}")
    return metrics


def selected_baselines(cfg: DictConfig) -> dict:
    """The baselines to test beside the model (``{name: model config}``).  ``baselines=null`` and ``baselines={}``
    both switch them off: Hydra merges ``{}`` into the composed group (a no-op), so the command line's own
    ``baselines={}`` is honoured here."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized() and any(o.replace(" ", "") in ("baselines={}", "baselines=null", "baselines=[]")
                                         for o in HydraConfig.get().overrides.task):
        return {}
    return {name: bcfg for name, bcfg in (cfg.get("baselines") or {}).items()
            if isinstance(bcfg, DictConfig) and "_target_" in bcfg}


def _test_baseline(cfg: DictConfig, name: str, bcfg: DictConfig, dm) -> dict:
    """Validate and test a baseline (nothing trained) on the same datamodule, neighbours and splits."""
    started = time.perf_counter()
    model = hydra.utils.instantiate(bcfg)
    metrics, arrays = evaluate_model(cfg, model, dm)
    return {"method": getattr(model, "method", name), "scene": dm.scene_name, "n_test": int(len(arrays["ids"])),
            "trainable_parameters": int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
            "metrics": metrics, "seconds": round(time.perf_counter() - started, 3), "_arrays": arrays}


def save_samples(out: Path, scene: str, method: str, arrays: dict, n: int) -> Path:
    """The first ``n`` test spectra of an evaluation (lowest ids: the same positions for every method on a
    scene) as ``samples/<scene>__<method>.npz`` (``pred``, ``target``: uint8 [n, 90, 360]; ``ids``), for
    graf-report's true-vs-predicted grids."""
    import numpy as np

    order = np.argsort(np.asarray(arrays["ids"]))[:n]
    q = lambda x: np.clip(np.rint(np.asarray(x)[order] * 255.0), 0, 255).astype(np.uint8)  # noqa: E731
    path = out / "samples" / f"{scene}__{method}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_npz(path, pred=q(arrays["pred"]), target=q(arrays["target"]), ids=np.asarray(arrays["ids"])[order])
    return path


def format_metrics_table(rows: list[dict]) -> str:
    """A plain-text table of the four test metrics (and the validation PSNR), one row per results dict."""
    head = (f"{'method':<22}{'scene':<16}{'n_test':>7}{'MSE':>10}{'PSNR':>9}{'SSIM':>8}{'LPIPS':>8}"
            f"{'val PSNR':>10}{'reliance dB':>13}")
    lines = [head, "-" * len(head)]
    for r in rows:
        m = r["metrics"]

        def f(key, spec):
            v = m.get(key)
            width = spec.split(".")[0]
            return format(v, spec) if v is not None and not math.isnan(v) else format("n/a", f">{width}")

        lines.append(f"{r['method']:<22}{r['scene']:<16}{r['n_test']:>7}{f('test/mse', '10.4f')}"
                     f"{f('test/psnr', '9.2f')}{f('test/ssim', '8.3f')}{f('test/lpips', '8.3f')}"
                     f"{f('val/psnr', '10.2f')}{f('test/reliance_db', '13.2f')}")
    return "\n".join(lines)


def sweep_value(cfg: DictConfig, metrics: dict, objects: dict | None = None):
    """The value(s) a sweep optimises (``optimized_metric``: one name, or a list for a multi-objective search;
    see :mod:`graf.sweeps.objectives` for the names).  Only validation metrics and costs measured on
    validation data are accepted: nothing is chosen on the test split.  A NaN or missing metric is returned
    as NaN for the Optuna sweeper (which records the trial as failed) and as -inf for Hydra's basic sweeper."""
    from graf.sweeps.objectives import objective_values

    names = cfg.get("optimized_metric")
    if not names:
        return 0.0
    single = isinstance(names, str)
    values = objective_values([names] if single else list(names), metrics, objects or {})
    if not cfg.get("optuna_trial"):  # the worst value instead (a cost: +inf)
        worst = [float("inf") if str(n).startswith("cost/") else float("-inf") for n in ([names] if single else names)]
        for n, v in zip([names] if single else names, values):
            if not math.isfinite(v):
                log.warning("optimized metric %s is %s; reporting the worst value", n, v)
        values = [v if math.isfinite(v) else w for v, w in zip(values, worst)]
    return values[0] if single else values
