"""A run resolved once: :class:`RunSpec`, the typed reading of a composed config that the run functions take.

A config names its scenes as Hydra composes them (``scene=conference_v1`` -> ``scene.conference_v1: {...}``,
``eval_scene=heldout`` -> a placeholder, a bench's flat ``scenes.<key>``); this module is the one place that reads
those selections (:func:`_scene_selection`).  The run functions (:mod:`graf.run.build`, :mod:`graf.run.train`,
:mod:`graf.run.finetune`, the case studies and the simulator's commands) read a spec's fields instead: the scenes
trained and tested on, the bands, the neighbour selector's config, the training steps and the output folder.

Resolving a run (the study budget, the baselines switch, the fine-tuning base, the held-out layouts) happens in
:func:`graf.run.resolve.resolve_run`; :meth:`RunSpec.of` reads a config that is already resolved.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from hydra import compose
from omegaconf import DictConfig, OmegaConf, open_dict

from graf.app.config import CONF_DIR, output_dir
from graf.errors import ConfigError

log = logging.getLogger("graf")


def _scene_selection(node) -> tuple[DictConfig, ...]:
    """The scene configs a ``scene`` or ``eval_scene`` node selects, in order.  ``scene=conference_v1`` composes
    to ``scene.conference_v1: {...}`` and ``scene=[conference_v1,office_v1]`` to one entry per scene (Hydra's
    list selection; each option places ``scene_catalog/<name>`` under its own name); a flat config with a
    ``_target_`` (graf-bench's ``scenes.<key>``) is one scene."""
    if node is None:
        return ()
    if isinstance(node, DictConfig) and "_target_" in node:
        return (node,)
    return tuple(v for v in node.values() if isinstance(v, DictConfig) and "_target_" in v)


@dataclass(frozen=True, eq=False)
class RunSpec:
    """One run, read once from its composed config.

    ``cfg`` is the config that runs (results.json records it); the other fields are what the run functions read
    of it.  ``eval_scenes`` is empty for a within-scene run (``eval_scene=same``): the training scenes are tested,
    at ``eval_band`` when one is set."""

    cfg: DictConfig
    scenes: tuple[DictConfig, ...]  # trained on (scene=)
    eval_scenes: tuple[DictConfig, ...]  # tested on (eval_scene=); empty: the training scenes
    band: DictConfig | None  # band=: the simulated scenes' carrier (a measured scene keeps its own)
    eval_band: str | None  # eval_band=: the training scenes tested at another band
    neighbors: DictConfig | None  # neighbors=: the selector's config
    steps: int | None  # trainer.max_steps (a study's budget once resolved)
    output_dir: Path

    @classmethod
    def of(cls, cfg: DictConfig) -> RunSpec:
        """The spec of a composed (and resolved) config."""
        trainer = cfg.get("trainer") or {}
        steps = trainer.get("max_steps") if isinstance(trainer, DictConfig) else None
        return cls(
            cfg=cfg,
            scenes=_scene_selection(cfg.get("scene")),
            eval_scenes=_scene_selection(cfg.get("eval_scene")),
            band=cfg.get("band"),
            eval_band=None if cfg.get("eval_band") is None else str(cfg.get("eval_band")),
            neighbors=cfg.get("neighbors"),
            steps=steps if isinstance(steps, int) and steps >= 0 else None,
            output_dir=output_dir(cfg),
        )

    @property
    def scene_names(self) -> list[str]:
        return [str(c.get("name")) for c in self.scenes]

    @property
    def eval_scene_names(self) -> list[str]:
        return [str(c.get("name")) for c in self.eval_scenes]

    @property
    def tested_scenes(self) -> tuple[DictConfig, ...]:
        """The scenes the final evaluations test: ``eval_scenes``, else the training scenes."""
        return self.eval_scenes or self.scenes

    def one_scene(self, command: str) -> DictConfig:
        """The one scene of a command that works on one scene (graf-simulate, graf-oracle, graf-synthesize)."""
        if len(self.scenes) != 1:
            raise ConfigError(
                f"{command} works on one scene; scene= selects {len(self.scenes)} "
                f"({', '.join(self.scene_names) or 'none'})"
            )
        return self.scenes[0]


def family(scene: str) -> str:
    """A catalog scene's layout family: ``conference_v2`` -> ``conference`` (a scene without variants is its
    own family)."""
    return scene.rsplit("_v", 1)[0] if "_v" in scene and scene.rsplit("_v", 1)[1].isdigit() else scene


def heldout_scenes(train: list[str], heldout) -> list[str]:
    """``eval_scene=heldout``: the catalog scenes of the training scenes' families that the run does not train
    on (``heldout: auto``; not the validation layouts, ``validation_only``, which are never tested), or those of a
    list that share a family with a training scene."""
    families = {family(n) for n in train}
    if heldout == "auto":
        paths = sorted((CONF_DIR / "scene_catalog").glob("*.yaml"))
        candidates = [p.stem for p in paths if "\nvalidation_only: true" not in p.read_text()]
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
    train = RunSpec.of(cfg).scene_names
    names = heldout_scenes(train, ev.heldout)
    cfg = cfg.copy()
    with open_dict(cfg):
        if not names:
            log.info("eval_scene=heldout: no held-out layout of %s: testing within-scene", ", ".join(train))
            cfg.eval_scene = None
            return cfg
        composed = compose(config_name="train", overrides=[f"eval_scene=[{','.join(names)}]"])
        cfg.eval_scene = OmegaConf.create(OmegaConf.to_container(composed.eval_scene, resolve=False))
    log.info("eval_scene=heldout: testing on %s (held out from training on %s)", ", ".join(names), ", ".join(train))
    return cfg


def as_spec(run: RunSpec | DictConfig) -> RunSpec:
    """``run`` itself when it is a spec; a composed config's spec (:meth:`RunSpec.of`) otherwise."""
    return run if isinstance(run, RunSpec) else RunSpec.of(run)
