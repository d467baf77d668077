"""What one run produced, as typed records: :class:`RunRecord` is ``results.json`` (read back with
:meth:`RunRecord.read`), its parts the timing, training, resume, fine-tuning and checkpoint facts; :class:`RunResult`
is what ``train(cfg)`` / ``evaluate(cfg)`` return beside the metrics (``metrics, run = train(cfg)``).

A field marked optional is left out of ``results.json`` when it is None (a run that trained nothing has no
``training``), so the file keeps the keys it always had.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:  # for annotations only: build imports this module's neighbors, not the other way round
    from graf.run.build import BuiltRun


def optional(**kwargs):
    """A field left out of the JSON when None."""
    return field(default=None, metadata={"omit_if_none": True, **kwargs})


class Record:
    """A dataclass that is written to, and read from, plain JSON (nested records, lists and dicts of them)."""

    def to_json(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.metadata.get("json") is False or (value is None and self.omitted(f)):
                continue
            out[f.metadata.get("key", f.name)] = encode(value)
        return out

    def omitted(self, f: dataclasses.Field) -> bool:
        """Whether a None field is left out (the optional ones)."""
        return bool(f.metadata.get("omit_if_none"))

    @classmethod
    def from_json(cls, data: dict):
        hints = typing.get_type_hints(cls)
        kwargs = {}
        for f in dataclasses.fields(cls):
            key = f.metadata.get("key", f.name)
            if f.metadata.get("json") is not False and key in data:
                kwargs[f.name] = decode(hints[f.name], data[key])
        return cls(**kwargs)


def encode(value):
    if isinstance(value, Record):
        return value.to_json()
    if isinstance(value, dict):
        return {k: encode(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [encode(v) for v in value]
    return value


def decode(tp, value):
    """``value`` (plain JSON) as the annotated type ``tp``: records, and lists and dicts of records."""
    if value is None:
        return None
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return decode(inner[0], value) if len(inner) == 1 else value
    if isinstance(tp, type) and issubclass(tp, Record):
        return tp.from_json(value)
    if origin is list and args:
        return [decode(args[0], v) for v in value]
    if origin is dict and len(args) == 2:
        return {k: decode(args[1], v) for k, v in value.items()}
    return value


@dataclass
class Timing(Record):
    """Wall seconds of the run's parts: the fit (when it trained), the final validation, test and reliance passes,
    and the whole test loop per test spectrum (the headline evaluation's)."""

    fit_s: float | None = None
    fit_steps: int | None = None
    fit_s_per_step: float | None = None
    val_s: float | None = None
    test_s: float | None = None
    reliance_s: float | None = None
    test_s_per_spectrum: float | None = optional()

    def omitted(self, f: dataclasses.Field) -> bool:
        return f.name.startswith("fit_") and self.fit_s is None or super().omitted(f)


@dataclass
class Training(Record):
    """The training length: the steps asked and reached, and why training stopped before ``max_steps``."""

    max_steps: int
    max_epochs: int
    start_step: int
    global_step: int
    steps_trained: int
    epochs_trained: int
    stopped_early: bool
    world_size: int
    targets_seen: int | None = optional()
    batches_on_fewer_threads: int | None = optional()  # beside busy processes (graf.callbacks.ThreadsBesideLoad)
    stop_reason: str | None = optional()
    own_limit: bool | None = optional()


@dataclass
class Resumed(Record):
    """The checkpoint a training run resumed from, its settings, and the trainer settings changed since."""

    checkpoint: str
    global_step: int
    checkpoint_settings: dict | None
    changed: dict


@dataclass
class Finetune(Record):
    """A run that started from a checkpoint's weights (``finetune.init_from``): fine-tuned or tested zero-shot."""

    init_from: str
    mode: str
    fraction: float | None
    seed: int
    test_pool: str | None
    n_measured: int
    n_train: int
    steps: int
    lr: float | None
    base_steps: int
    base_scenes: dict | None


@dataclass
class CheckpointInfo(Record):
    """The checkpoint graf-eval tested (its model config, ``model``, is the run's ``config.model``)."""

    path: str
    global_step: int
    class_name: str = field(metadata={"key": "class"})
    layout: int = 1
    hyper_parameters: dict = field(default_factory=dict)
    applied_overrides: dict = field(default_factory=dict)


@dataclass
class Versions(Record):
    """The versions a run was made with (results.json ``versions``)."""

    graf: str
    torch: str
    python: str


@dataclass
class BaselineFigures(Record):
    """A baseline's figures on one test scene (results.json ``baselines.<method>``)."""

    metrics: dict
    seconds: float
    trainable_parameters: int


@dataclass
class SceneEvaluation(Record):
    """One test scene's figures (results.json ``evaluations[]``: a run tested on other or several scenes)."""

    eval_scene: str
    within_scene: bool
    metrics: dict
    n_test: int
    band_hz: float
    scene_index: int
    splits: dict
    timing: Timing
    baselines: dict[str, BaselineFigures]


@dataclass
class RunRecord(Record):
    """``results.json``: what one graf-train or graf-eval run produced (the first test scene's figures are the
    headline), with the config that ran, its timing, device and versions.  ``scene`` names the scenes the model
    was trained on (``train_scenes`` joined by ``+``; a zero-shot test's: its checkpoint's), ``eval_scene`` the
    headline's test scene."""

    method: str
    scene: str
    train_scenes: list[str]
    eval_scene: str
    within_scene: bool
    band_hz: float
    train_bands_hz: list[float]
    n_train: int
    n_test: int
    metrics: dict
    seconds: float
    config: dict
    task: str
    eval_split: str
    split_source: str
    splits: dict
    trainable_parameters: int
    global_step: int
    device: str
    versions: Versions
    timing: Timing
    ray_sampling: dict | None = optional()
    checkpoint: CheckpointInfo | None = optional()
    predictions: str | None = optional()
    figure: str | None = optional()
    baselines: dict[str, BaselineFigures] | None = optional()
    evaluations: list[SceneEvaluation] | None = optional()
    training: Training | None = optional()
    resumed: Resumed | None = optional()
    finetune: Finetune | None = optional()
    scene_table: dict | None = optional()
    regime: str | None = optional()
    per_spectrum: str | None = optional()  # per_spectrum.csv.gz (graf.run.per_spectrum)
    prediction_sha256: dict | None = optional()  # {test scene: {method: sha256 of its predictions}}
    schedule: dict | None = optional()  # the learning-rate schedule that ran (graf.models.schedule)
    # {test scene: {"index", "source"}}: the scene index each test scene was given and why (trained, same place at
    # another band, unseen: graf.data.fingerprint.eval_scene_index)
    scene_indices: dict | None = optional()

    @classmethod
    def read(cls, path: Path) -> RunRecord:
        return cls.from_json(json.loads(Path(path).read_text()))

    def scene_metrics(self) -> list[dict]:
        """Every test scene's figures, the headline's first."""
        return [e.metrics for e in self.evaluations] if self.evaluations else [self.metrics]


@dataclass(eq=False)
class RunResult:
    """What a task returns beside its metrics: the output folder, the record it wrote, the objects it built
    (model, datamodules, trainer), and for a study job not run, why (``skipped``) or that it had finished before
    (``scene_metrics`` then come from its results.json)."""

    output_dir: Path
    record: RunRecord | None = None
    built: BuiltRun | None = None
    skipped: str | None = None
    finished_before: bool = False
    scene_metrics: list[dict] = field(default_factory=list)


class Results(NamedTuple):
    """What ``train(cfg)`` and ``evaluate(cfg)`` return: ``metrics, run = train(cfg)``."""

    metrics: dict
    run: RunResult


def finished_scene_metrics(done: dict[str, Any]) -> list[dict]:
    """Every test scene's figures of a results.json read as it is (a study job finished before, perhaps by an
    older version)."""
    if done.get("evaluations"):
        return [e["metrics"] for e in done["evaluations"]]
    return [done["metrics"]] if "metrics" in done else []


@dataclass
class RunFacts:
    """What a task knows of its run before testing it: which task, when it started (``time.perf_counter()``),
    the fit's timing, and what it trained, resumed, fine-tuned or tested (a checkpoint, graf-eval)."""

    task: str
    started: float
    timing: Timing = field(default_factory=Timing)
    training: Training | None = None
    resumed: Resumed | None = None
    finetune: Finetune | None = None
    checkpoint: CheckpointInfo | None = None
