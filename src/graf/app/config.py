"""The run's configuration: where the configs are, the scenes and bands a config selects, layout families and
held-out layouts, the run's settings, and the wrapper every task runs in.

Nothing here builds a model or touches data: :mod:`graf.run.build` does, from what these functions return.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from graf.config_home import CONF_DIR as CONF_HOME_DIR
from graf.errors import ConfigError, as_override, is_user_error, user_message

log = logging.getLogger("graf")

# The configs ship inside the package (src/graf/conf; conf/ in the checkout links to it).  Every
# @hydra.main reads them as a package resource, so an installed wheel works from any folder; add a
# folder of your own with Hydra's --config-dir.  CONF_DIR is the same folder on disk.
CONF_PATH = "pkg://graf.conf"
CONF_DIR = CONF_HOME_DIR  # graf.config_home's: the folder is named once


def output_dir(cfg: DictConfig) -> Path:
    """The run's output folder (``paths.output_dir``; the working folder outside a Hydra app)."""
    try:
        return Path(cfg.paths.output_dir)
    except Exception:  # ${hydra:...} outside a Hydra app
        return Path.cwd()


def task_wrapper(task):
    """Run a task; on failure log the exception (and the output folder) before re-raising; always close
    the loggers (wandb included), so a failed run in a sweep leaves a finished, inspectable record."""

    @functools.wraps(task)
    def wrapped(cfg: DictConfig, *args, **kwargs):
        try:
            check_shared_run_folder()
            return task(cfg, *args, **kwargs)
        except Exception as exc:
            if (is_user_error(exc) or hasattr(exc, "exit_code")) and os.environ.get("HYDRA_FULL_ERROR") != "1":
                log.error(
                    "%s failed: %s (output folder: %s)",
                    cfg.get("task_name", "task"),
                    user_message(exc, cfg),
                    output_dir(cfg),
                )
            else:
                log.exception("%s failed; output folder: %s", cfg.get("task_name", "task"), output_dir(cfg))
            raise
        finally:
            # only a run with the wandb logger has imported wandb: never import it here (it takes seconds, and a
            # second Ctrl+C during that import printed a second traceback)
            wandb = sys.modules.get("wandb")
            if getattr(wandb, "run", None) is not None:
                wandb.finish()

    return wrapped


# the command line's ways to switch the baselines off, and the value each leaves in the config
BASELINES_OFF = {"baselines={}": {}, "baselines=[]": {}, "baselines=null": None}


def with_baselines_switch(cfg: DictConfig) -> DictConfig:
    """The run's config with the command line's ``baselines={}`` (or ``[]``, ``null``) applied: Hydra merges ``{}``
    into the composed group (a no-op), so the config would still list ``knn`` though no baseline runs, and
    results.json (whose ``config.baselines`` graf-aoa reads) must record the config that ran."""
    if not HydraConfig.initialized():
        return cfg
    off = [
        BASELINES_OFF[o.replace(" ", "")]
        for o in HydraConfig.get().overrides.task
        if o.replace(" ", "") in BASELINES_OFF
    ]
    if not off or not cfg.get("baselines"):
        return cfg
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.baselines = off[-1]
    return cfg


def check_int(value, key: str, low: int | None = 1, none: bool = False) -> int | None:
    """``value``, the setting ``key``, when it is a whole number of at least ``low`` (None allowed when ``none``);
    else a :class:`ConfigError` naming both.  Checked, never cast: 2.5, true and "3" are refused."""
    if value is None and none:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or (low is not None and value < low):
        what = "a whole number" + ("" if low is None else f" >= {low}") + (" or null" if none else "")
        raise ConfigError(f"{key}={as_override(value)}: must be {what}")
    return value


def check_bool(value, key: str) -> bool:
    """``value``, the setting ``key``, when it is true or false (a YAML or command-line boolean); else a
    :class:`ConfigError` naming both (a string such as "maybe" or "no" is refused, never read as true)."""
    if not isinstance(value, bool):
        raise ConfigError(f"{key}={as_override(value)}: must be true or false")
    return value


def override_key(override: str) -> str:
    """The key a command-line override sets: ``model`` for ``model=knn``, ``+trainer.x`` and ``~trainer.x`` ->
    ``trainer.x``."""
    return override.split("=", 1)[0].lstrip("+~")


def launched_ranks() -> int:
    """How many processes an outside launcher started for this command: torchrun's (and Lightning's children's)
    ``WORLD_SIZE``, srun's ``SLURM_STEP_NUM_TASKS``; 1 for a plain command."""
    for key in ("WORLD_SIZE", "SLURM_STEP_NUM_TASKS"):
        try:
            n = int(os.environ.get(key) or 1)
        except ValueError:
            continue
        if n > 1:
            return n
    return 1


def check_shared_run_folder() -> None:
    """Refuse a run started as several processes (torchrun, srun) without ``hydra.run.dir``: each process would
    name its own folder after the second it started in, so rank 0 would write the run's files in one folder and
    the others would look for them (a base model trained on the fly, a checkpoint) in another.  Lightning's own
    launcher passes its folder to the processes it starts; a multirun's folders are named once by its launcher."""
    n = launched_ranks()
    if n < 2 or not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.RUN:
        return
    if any(override_key(o) == "hydra.run.dir" for o in HydraConfig.get().overrides.hydra):
        return
    raise ConfigError(
        f"{n} processes were started for this run (torchrun / srun), and each would name its own output folder "
        "after the second it started in: give them one, e.g. hydra.run.dir=outputs/ddp_run"
    )


def _band_folders() -> list[Path]:
    """Where band files are looked for: the running Hydra app's ``file://`` config sources in its search order (a
    user's own config folder from ``hydra.searchpath`` among them), then graf's own folder."""
    folders = []
    if HydraConfig.initialized():
        for source in HydraConfig.get().runtime.config_sources:
            if source.schema == "file" and (Path(source.path) / "band").is_dir():
                folders.append(Path(source.path) / "band")
    return folders + [CONF_DIR / "band"]


def band_choices() -> list[str]:
    """The options of the ``band`` config group: graf's and those of the app's search path."""
    return sorted({p.stem for folder in _band_folders() for p in folder.glob("*.yaml")})


def load_band_config(name: str) -> DictConfig:
    """Band ``name``'s config, found where the run's ``band=`` finds it: a band file of one's own config folder
    (``hydra.searchpath``) serves as an ``eval_band`` or as a scene's own ``band:`` too."""
    for folder in _band_folders():
        if (folder / f"{name}.yaml").is_file():
            return OmegaConf.load(folder / f"{name}.yaml")
    raise ConfigError(f"unknown band {name!r}: one of {', '.join(band_choices())}")


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
    raise ConfigError(
        f"scene {scene_cfg.get('name', '?')!r} does not say its carrier frequency: add "
        f"band=<one of {', '.join(band_choices())}> (the band its spectra were measured at)"
    )


def hz(v: float) -> str:
    return f"{v / 1e9:.3g} GHz" if v >= 1e9 else f"{v / 1e6:.4g} MHz"


def run_settings(cfg: DictConfig) -> dict:
    """The settings of a training run that its checkpoints record (``checkpoint["graf"]["run"]``: data,
    neighbors, seed, trainer), so that resuming with other ones is refused or recorded
    (:func:`graf.run.train.check_resume`)."""
    c = OmegaConf.to_container(cfg, resolve=True)
    trainer = {k: v for k, v in (c.get("trainer") or {}).items() if k not in ("_target_", "default_root_dir")}
    return {"data": c.get("data"), "neighbors": c.get("neighbors"), "seed": c.get("seed"), "trainer": trainer}


SEED_MAX = 2**32 - 1  # numpy's (and so Lightning's seed_everything's) largest seed


def check_run_settings(cfg: DictConfig) -> None:
    """Top-level settings that must be integers in a range, checked before anything is built or moved (one clear
    error): ``seed`` in numpy's range 0..2**32-1, ``torch_threads`` >= 1, and no second setting of how many
    spectra are tested (``trainer.limit_test_batches``: ``data.test_subset`` is the one)."""
    for key, low, high in (("seed", 0, SEED_MAX), ("torch_threads", 1, None)):
        v = cfg.get(key)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, int) or v < low or (high is not None and v > high):
            span = f" >= {low}" if high is None else f" from {low} to {high}"
            raise ConfigError(f"{key} must be an integer{span}, got {v!r}")
    limit = (cfg.get("trainer") or {}).get("limit_test_batches", 1.0)
    if limit not in (None, 1.0):
        raise ConfigError(
            f"trainer.limit_test_batches={limit}: how many spectra a run tests is data.test_subset=N (N per scene; "
            "data.test_subset_seed=null for the first N of the split, as the first batches were)"
        )
