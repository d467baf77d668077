"""Shared LightningModule behaviour of every method: the evaluation protocol, its metrics, and what a
checkpoint records about the model that wrote it.

A method implements :meth:`predict_spectra` (batch -> ``[B, 90, 360]``) and, if it learns, ``training_step``
and ``configure_optimizers``.  Validation and test metrics are per-spectrum means over the evaluated split
(``val/...`` and ``test/...``: ``mse``, ``psnr``, ``ssim``, ``lpips``); predictions are clamped to [0, 1] first.

Every checkpoint carries ``checkpoint["graf"] = {"target": <class path>, "layout": <LAYOUT>, "scenes": {name:
{"index", "band_hz", "fingerprint"}}}`` (the scenes it was trained on, identified by content:
:mod:`graf.data.fingerprint`).  A class
bumps ``LAYOUT`` when its weights change meaning (and says why in ``LAYOUT_CHANGES``); loading a checkpoint
of another layout, or of another class, is refused with a message that names the file and the reason
(:func:`check_checkpoint`).

Checkpoints are read safely (:func:`read_checkpoint`, :func:`safe_loading`): weights only (tensors, plain containers
and numbers), with an allow-list of the few other types a checkpoint of this project may hold
(:data:`CHECKPOINT_TYPES`).  A file that holds anything else (a crafted pickle whose objects would run code as they
are loaded) is refused with one line, and nothing in it runs; the class a checkpoint names is imported only when it
is one of graf's methods or of a plugin's (:func:`checkpoint_class`).
"""

from __future__ import annotations

import collections
import math
import pickle
import re
import sys
import typing
import warnings
from pathlib import Path
from typing import Protocol, runtime_checkable

import lightning as L
import torch
from hydra.utils import get_class
from omegaconf import DictConfig, ListConfig
from omegaconf import base as omegaconf_base
from omegaconf import nodes as omegaconf_nodes

from graf.data.fingerprint import register_scene
from graf.errors import UserError
from graf.metrics import spectrum_metrics
from graf.models.schedule import exponential_record, run_steps, schedule_length
from graf.plugins import is_plugin_module


class CheckpointError(UserError):
    """A checkpoint that cannot be used as asked; the message names the file and why."""


def class_path(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


# What a checkpoint may hold besides tensors, plain containers and numbers (torch's weights-only load): the
# hyperparameters of a model built from a config (OmegaConf containers, as Lightning saves them) and the plain
# types those are pickled with.  Nothing here runs code when loaded.
CHECKPOINT_TYPES: tuple = (
    DictConfig,
    ListConfig,
    omegaconf_base.ContainerMetadata,
    omegaconf_base.Metadata,
    omegaconf_nodes.AnyNode,
    omegaconf_nodes.StringNode,
    omegaconf_nodes.IntegerNode,
    omegaconf_nodes.FloatNode,
    omegaconf_nodes.BooleanNode,
    typing.Any,
    dict,
    list,
    int,
    float,
    collections.defaultdict,
    collections.OrderedDict,
)


def safe_loading():
    """The context in which every checkpoint is loaded (:func:`read_checkpoint`, and Lightning's own loads with
    ``weights_only=True``): torch's weights-only unpickler with :data:`CHECKPOINT_TYPES` allowed."""
    return torch.serialization.safe_globals(list(CHECKPOINT_TYPES))


def refused_load(path, exc: BaseException) -> CheckpointError:
    """The one-line error for a file torch's weights-only load refused: the type it would not load when torch names
    one (a pickle of foreign objects, possibly crafted to run code), else what torch found."""
    text = str(exc)
    found = re.search(r"unsupported (?:global:? )?GLOBAL ([\w.]+)", text, re.IGNORECASE)
    if found:
        return CheckpointError(
            f"{path}: is not a checkpoint of this project: it holds an object of type {found.group(1)}, which graf's "
            "checkpoints never hold; not loaded (loading it could run code in it)"
        )
    torch_own = ("Weights only load failed", "Check the documentation", "Please file an issue", "(1)", "(2)")
    lines = [ln.strip() for ln in text.split("WeightsUnpickler error:")[-1].splitlines()]
    what = next((ln for ln in lines if ln and not ln.startswith(torch_own)), "not a weights-only pickle")
    return CheckpointError(f"{path}: is not a readable checkpoint ({what}; read as weights only)")


def read_checkpoint(path, lightning: bool = True) -> dict:
    """A Lightning checkpoint as a dict, with clear errors for a missing, unreadable or foreign file.  Loaded
    weights only (:func:`safe_loading`): a file holding other objects is refused and none of them runs.
    ``lightning=False``: any dict (the records graf-curves reads need no ``state_dict``)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file does not exist")
    try:
        with safe_loading(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Detected pickle protocol")  # a plain pickle: refused below
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise refused_load(path, exc) from None
    except Exception as exc:
        first = (str(exc).strip().splitlines() or ["the file is empty or cut short"])[0]
        raise CheckpointError(f"{path}: is not a readable checkpoint ({type(exc).__name__}: {first})") from None
    if not isinstance(ckpt, dict) or (lightning and "state_dict" not in ckpt):
        raise CheckpointError(f"{path}: is not a Lightning checkpoint (no state_dict)")
    return ckpt


def _imported_class(name: str):
    """The object ``name`` names in a module already imported (nothing imported, nothing run), or None."""
    parts = name.split(".")
    for i in range(len(parts) - 1, 0, -1):
        module = sys.modules.get(".".join(parts[:i]))
        if module is not None:
            obj = module
            for attr in parts[i:]:
                obj = getattr(obj, attr, None)
            return obj
    return None


def checkpoint_class(target, path) -> type:
    """The method class a checkpoint names (``checkpoint["graf"]["target"]``), a :class:`SpectrumModule`: one of
    graf's, one of a plugin's (a module ``GRAF_PLUGINS`` loaded, or a submodule of one: :mod:`graf.plugins`), or
    one in a module already imported (a script's own).  Any other module is not imported (a crafted file naming
    one must not make graf run its code): refused in one line saying how to load it."""
    name = str(target)
    module = name.rpartition(".")[0]
    prefixes = [".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1)]
    if name.startswith("graf.") or any(is_plugin_module(p) for p in prefixes):
        try:
            cls = get_class(name)
        except Exception:
            raise CheckpointError(
                f"{path}: names the class {name}, which this version of graf or of its plugin does not have"
            ) from None
    else:
        cls = _imported_class(name)
        if cls is None:
            raise CheckpointError(
                f"{path}: names the class {name!r}, which is not one of graf's methods nor of a plugin loaded: load "
                f"the plugin that defines it (GRAF_PLUGINS={module}); not imported"
            )
    if not (isinstance(cls, type) and issubclass(cls, SpectrumModule)):
        raise CheckpointError(f"{path}: names {name}, which is not one of graf's methods (a SpectrumModule)")
    return cls


def check_checkpoint(ckpt: dict, cls: type, path) -> None:
    """Refuse a checkpoint written by another class, or by an older layout of ``cls`` (see module doc)."""
    info = ckpt.get("graf") or {}
    target = info.get("target")
    if target is not None and target != class_path(cls):
        raise CheckpointError(f"{path}: holds a {target} checkpoint, not {class_path(cls)}")
    layout = int(info.get("layout", 1))
    want = int(getattr(cls, "LAYOUT", 1))
    if layout != want:
        changes = getattr(cls, "LAYOUT_CHANGES", {})
        why = "; ".join(f"layout {v}: {changes[v]}" for v in sorted(changes) if layout < v <= want)
        raise CheckpointError(
            f"{path}: was written by {cls.__name__} layout {layout}; this version reads layout "
            f"{want} only, and the weights do not carry over{': ' + why if why else ''}. "
            "Retrain (or use the version that wrote it)."
        )


def adam_exponential_decay(module, lr: float, lr_decay: float, decay_steps: int | None) -> dict:
    """Adam with the learning rate multiplied by ``lr_decay`` over ``decay_steps`` optimiser steps (exponential,
    stepped every step; None: over the run's ``max_steps``, :mod:`graf.models.schedule`): the optimiser of GRaF
    and KNN-DL, in Lightning's return format.  What ran is kept in ``module.schedule_record``."""
    length = schedule_length(module, decay_steps, "decay_steps")
    module.schedule_record = exponential_record(lr, lr_decay, length, run_steps(module))
    opt = torch.optim.Adam(module.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=lr_decay ** (1.0 / length))
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}


@runtime_checkable
class Method(Protocol):
    """What the platform asks of a method, and all it reads of one (graf-train, graf-eval, the records, the
    studies): docs/extending.md, "Add a method".  :class:`SpectrumModule` gives every member a default but
    :meth:`predict_spectra`.

    method: its name in ``results.json``, the tables and the intervals (``graf-ray-weights``, ``knn``).
    uses_neighbors: whether a prediction reads the neighbors' spectra (then its test also measures its neighbor
        reliance); False: a field of the scenes it was trained on (NeRF2, RF-GS), which reads no neighbor.
    per_scene: True: one scene's model (RF-GS), refused on a scene it was not trained on and on several scenes at
        once (:func:`graf.run.build.check_per_scene`); NeRF2 is False, as it may be tested zero-shot (the studies do).
    has_trainable_parameters: False: nothing is trained (KNN), ``graf-train`` only tests it.
    INFERENCE_SETTINGS: settings that change how fast it predicts, not what: graf-eval may change them on a
        trained checkpoint.
    schedule_record: the learning-rate schedule that ran (``results.json`` ``schedule``), or None.
    predict_spectra: a batch (``tgt_pos [B, 3]``, ``src_pos [B, L, 3]``, ``src_spectra [B, L, 90, 360]``,
        ``src_mask [B, L]``, the scene's geometry) -> spectra ``[B, 90, 360]`` in [0, 1].
    upgrade_hparams: a checkpoint's hyperparameters in the method's current form (graf-eval, a resume).

    A method that renders rays (GRaF, NeRF2; ``renders_rays`` True) also gives what graf-bench and the records read
    of its rays; the defaults say "not a ray renderer":

    renders_rays: True where ``prepare(batch) -> ctx`` and ``render(ctx, pix [B, R]) -> [B, R]`` render a subset of
        a spectrum's pixels (graf-bench's light warm-up renders one chunk of ``chunk_rays`` through them).
    rays_per_step: pixels one training step renders over a batch (None: whole spectra).
    chunk_rays: pixels rendered at once at inference (None: whole spectra).
    samples_per_ray / mean_samples_per_ray: the most and the mean samples per ray of each batch item (None: no
        rays); ray_sampling: their summary on one scene for ``results.json`` (None: no rays).
    """

    method: str
    uses_neighbors: bool
    per_scene: bool
    has_trainable_parameters: bool
    INFERENCE_SETTINGS: tuple[str, ...]
    schedule_record: dict | None
    renders_rays: bool
    rays_per_step: int | None
    chunk_rays: int | None

    def predict_spectra(self, batch: dict) -> torch.Tensor: ...

    @staticmethod
    def upgrade_hparams(hparams: dict) -> dict: ...

    def samples_per_ray(self, batch: dict) -> list[int] | None: ...

    def mean_samples_per_ray(self, batch: dict) -> list[float] | None: ...

    def ray_sampling(self, geometry: dict) -> dict | None: ...


class SpectrumModule(L.LightningModule):
    """What every method is (GRaF, KNN, KNN-DL, NeRF2): a LightningModule that predicts spectra ``[B, 90, 360]`` in
    [0, 1] from a batch (:meth:`predict_spectra`), is validated and tested on the registered metrics
    (:mod:`graf.metrics.names`) and records its checkpoint layout (``LAYOUT``, ``LAYOUT_CHANGES``); the
    :class:`Method` interface, with a default for every member but :meth:`predict_spectra`."""

    uses_neighbors = True  # NeRF2 sets False: a per-scene field (its test measures no neighbor reliance)
    per_scene = False  # RF-GS sets True: tested only on the scene it was trained on (graf.run.build)
    INFERENCE_SETTINGS: tuple[str, ...] = ()
    schedule_record: dict | None = None  # set by the optimiser's schedule (graf.models.schedule)
    renders_rays = False  # GRaF and NeRF2: prepare(batch) and render(ctx, pix) render a subset of pixels
    rays_per_step: int | None = None  # pixels a training step renders over a batch; None: whole spectra
    chunk_rays: int | None = None  # pixels rendered at once at inference; None: whole spectra
    LAYOUT = 1
    LAYOUT_CHANGES: dict[int, str] = {}

    @property
    def method(self) -> str:
        """Its name in the records: the class name in kebab case without ``Module`` (``NeighborMean``:
        ``neighbor-mean``) unless the method says otherwise."""
        name = type(self).__name__.removesuffix("Module")
        return "".join(f"-{c.lower()}" if c.isupper() and i else c.lower() for i, c in enumerate(name))

    def __init__(self):
        super().__init__()
        self.val_metrics = spectrum_metrics("val/")
        self.test_metrics = spectrum_metrics("test/")

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["graf"] = {
            "target": class_path(type(self)),
            "layout": int(self.LAYOUT),
            "scenes": self.trained_scenes(),
        }
        if getattr(self, "run_settings", None):  # data, neighbors, seed, trainer: a resume is checked against them
            checkpoint["graf"]["run"] = self.run_settings

    def trained_scenes(self) -> dict:
        """``{scene name: {"index", "band_hz"}}``: the scenes this model was trained on, with the scene index
        and band each had (those of the checkpoint it was fine-tuned from, ``scene_table``, and the training
        datamodule's).  Checkpoints record it, so a later run gives a known scene its index back and an
        unseen one the one index it was not trained with, and can tell a cross-band transfer."""

        table = dict(getattr(self, "scene_table", None) or {})
        trainer = getattr(self, "_trainer", None)
        dm = getattr(trainer, "datamodule", None) if trainer is not None else None
        if getattr(dm, "sets", None):
            for d, fp, k in zip(dm.sets, dm.fingerprints(), dm.scene_index.tolist()):
                register_scene(table, d.name, fp, k)
        return table

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        check_checkpoint(checkpoint, type(self), "checkpoint")

    @staticmethod
    def upgrade_hparams(hparams: dict) -> dict:
        """A checkpoint's hyperparameters in the current form: as saved, unless the method's arguments changed
        (GRaF's: :mod:`graf.models.graf.legacy`)."""
        return dict(hparams)

    def samples_per_ray(self, batch: dict) -> list[int] | None:
        """The most samples on any ray of each batch item (ray renderers); None: the method renders no rays."""
        return None

    def mean_samples_per_ray(self, batch: dict) -> list[float] | None:
        """The mean samples per ray of each batch item (what a spectrum's cost is proportional to); by default
        :meth:`samples_per_ray` (every ray alike); None: no rays."""
        most = self.samples_per_ray(batch)
        return None if most is None else [float(s) for s in most]

    def ray_sampling(self, geometry: dict) -> dict | None:
        """For ray-rendering methods: samples per ray and the effective sample spacing on one scene, and whether
        ``max_samples`` capped them (the spacing is then longer than the method's nominal ``sample_spacing``
        wavelengths).  ``geometry``: the scene's batch geometry with a batch of one (``ray_length [1]``,
        ``wavelength [1]``, ``gw_pos [1, 3]``, ``gw_rot [1, 3, 3]``, ``bounds [1, 2, 3]``).  None for other methods."""
        most = self.samples_per_ray(geometry)
        if most is None:
            return None
        ray_length, wavelength = float(geometry["ray_length"][0]), float(geometry["wavelength"][0])
        S = int(most[0])
        span = float(ray_length) - float(getattr(self, "near", 0.0))
        nominal = float(getattr(self, "sample_spacing", 1.0))
        spacing = span / S / float(wavelength)
        return {
            "samples_per_ray": S,
            "sample_spacing_m": span / S,
            "sample_spacing_wavelengths": spacing,
            "nominal_spacing_wavelengths": nominal,
            "capped": bool(spacing > nominal * (1 + 1e-6)),
            "uncapped_samples": int(math.ceil(span / (nominal * float(wavelength)) - 1e-6)),
        }

    @property
    def has_trainable_parameters(self) -> bool:
        return any(p.requires_grad for p in self.parameters())

    def predict_spectra(self, batch: dict) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError(f"{type(self).__name__} must define predict_spectra (graf.models.base.Method)")

    def _eval_step(self, batch: dict, metrics) -> dict:
        pred = self.predict_spectra(batch).float().clamp(0.0, 1.0)
        target = batch["tgt_spectrum"].float()
        metrics.update(pred, target)
        self.log_dict(metrics, on_step=False, on_epoch=True, batch_size=pred.shape[0])
        per_spectrum = {  # [B] each (NaN for an empty target)
            name.split("/")[-1]: m.last_values for name, m in metrics.items() if hasattr(m, "last_values")
        }
        return {"pred": pred.detach(), "ids": batch["tgt_id"].detach(), "per_spectrum": per_spectrum}

    def validation_step(self, batch: dict, batch_idx: int) -> dict:
        return self._eval_step(batch, self.val_metrics)

    def test_step(self, batch: dict, batch_idx: int) -> dict:
        return self._eval_step(batch, self.test_metrics)
