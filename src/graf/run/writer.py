"""A tested run's record and what is made of it: :func:`run_record` assembles ``results.json``
(:class:`graf.run.record.RunRecord`) from the run and its evaluations, :func:`write_run` writes it and its files
(``predictions.npz``, ``spectra.png``, ``samples/``; the record last, atomically), :func:`print_summary` prints the
table.  :func:`test_and_report` does the three in turn.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import platform
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

import graf
from graf.io import atomic_write_json, atomic_write_npz, is_rank_zero
from graf.plotting import plot_spectra_grid
from graf.run.build import BuiltRun
from graf.run.evaluation import SceneTest, evaluate_scenes, ray_sampling, run_device
from graf.run.per_spectrum import (
    PER_SPECTRUM_FILE,
    evaluation_rows,
    predictions_sha256,
    write_per_spectrum,
)
from graf.run.record import RunFacts, RunRecord, RunResult, SceneEvaluation, Versions

log = logging.getLogger("graf")

RESULTS_FILE = "results.json"
PREDICTIONS_FILE = "predictions.npz"
FIGURE_FILE = "spectra.png"
# a finished run's files in its output folder (beside Hydra's .hydra/, the log and the loggers' folders)
RUN_FILES = (RESULTS_FILE, PREDICTIONS_FILE, PER_SPECTRUM_FILE, FIGURE_FILE, "samples", "preempted.json", "checkpoints")
# the name a replaced run's results.json keeps in its folder: tools that collect results.json under a folder
# (graf-table, graf-report) must not count the replaced run beside the one that replaced it
REPLACED_RESULTS = "results.replaced.json"


def test_and_report(cfg: DictConfig, built: BuiltRun, facts: RunFacts) -> tuple[dict, RunResult]:
    """Validate and test the built run (``cfg``: the config that ran), record it, write its files and print its
    table.  Returns the headline metrics and the run's result."""
    scenes = evaluate_scenes(cfg, built, facts.timing)
    record = run_record(cfg, built, scenes, facts)
    if is_rank_zero():  # the other ranks of a data-parallel run compute the same figures and write nothing
        write_run(cfg, built, record, scenes)
        print_summary(cfg, record, scenes, built.output_dir)
    return record.metrics, RunResult(built.output_dir, record=record, built=built, scene_metrics=record.scene_metrics())


def run_record(cfg: DictConfig, built: BuiltRun, scenes: list[SceneTest], facts: RunFacts) -> RunRecord:
    """results.json of a tested run; the first test scene's figures are the headline."""
    first, model, train_dm = scenes[0], built.model, built.datamodule
    dm, n_test = first.scene.datamodule, int(len(first.model.arrays["ids"]))
    timing = first.model.timing
    if n_test:  # the whole test loop (prediction and the four metrics) per spectrum
        timing = dataclasses.replace(timing, test_s_per_spectrum=round(timing.test_s / n_test, 4))
    method = model.method
    train_scenes = trained_scenes(train_dm, facts.finetune)
    return RunRecord(
        method=method,
        scene="+".join(train_scenes),
        train_scenes=train_scenes,
        eval_scene=first.scene.eval_scene,
        within_scene=bool(first.scene.within_scene),
        band_hz=float(dm.bands[0].frequency_hz),
        train_bands_hz=[float(b.frequency_hz) for b in train_dm.bands],
        n_train=dm.n_train,
        n_test=n_test,
        metrics=first.model.metrics,
        seconds=round(time.perf_counter() - facts.started, 3),
        config=OmegaConf.to_container(cfg, resolve=True),
        task=facts.task,
        eval_split=dm.eval_split,
        split_source="; ".join(d.split_source for d in dm.sets),
        splits=dm.split_summary(),
        trainable_parameters=int(sum(p.numel() for p in model.parameters() if p.requires_grad)),
        global_step=int(facts.checkpoint.global_step if facts.checkpoint else built.trainer.global_step),
        device=run_device(built.trainer, model),
        versions=Versions(graf.__version__, torch.__version__, platform.python_version()),
        timing=timing,
        ray_sampling=ray_sampling(model, dm),
        checkpoint=facts.checkpoint,
        predictions=PREDICTIONS_FILE if cfg.get("save_predictions") else None,
        figure=FIGURE_FILE if int(cfg.get("plot_count", 0)) > 0 and n_test else None,
        baselines={b.method: b.figures() for b in first.baselines} or None,
        evaluations=scene_evaluations(scenes, timing) if is_transfer(built, scenes) else None,
        training=facts.training,
        resumed=facts.resumed,
        finetune=facts.finetune,
        scene_table=built.scene_table or None,
        regime=str(cfg.regime) if cfg.get("regime") else None,
        per_spectrum=PER_SPECTRUM_FILE if per_spectrum_rows(method, scenes) else None,
        schedule=model.schedule_record,
        scene_indices={
            s.scene.eval_scene: {
                "index": int(s.scene.datamodule.scene_index[0]),
                "source": getattr(s.scene.datamodule, "scene_index_source", "trained"),
            }
            for s in scenes
        },
        prediction_sha256={
            s.scene.eval_scene: {
                method: predictions_sha256(s.model.arrays),
                **{b.method: predictions_sha256(b.arrays) for b in s.baselines},
            }
            for s in scenes
        },
    )


def per_spectrum_rows(method: str, scenes: list[SceneTest]) -> list[dict]:
    """Every test spectrum's metrics of the model and its baselines on every test scene."""
    rows = []
    for s in scenes:
        rows += evaluation_rows(s.scene.eval_scene, method, s.model.arrays)
        for b in s.baselines:
            rows += evaluation_rows(s.scene.eval_scene, b.method, b.arrays)
    return rows


def trained_scenes(train_dm, finetune) -> list[str]:
    """The scenes the run trained on: a zero-shot test trains nothing, so its model's are its checkpoint's
    (``finetune.base_scenes``, in scene-index order), not the scene it is tested on."""
    base = (finetune.base_scenes if finetune and finetune.mode == "zero-shot" else None) or {}
    if base:
        return sorted(base, key=lambda n: (base[n] or {}).get("index", 0))
    return [d.name for d in train_dm.sets]


def is_transfer(built: BuiltRun, scenes: list[SceneTest]) -> bool:
    """Whether the run's test scenes are other than its training scenes (or several): results.json then lists
    every one under ``evaluations``."""
    first = scenes[0].scene
    return len(scenes) > 1 or not first.within_scene or first.eval_scene != built.datamodule.scene_name


def scene_evaluations(scenes: list[SceneTest], headline_timing) -> list[SceneEvaluation]:
    return [
        SceneEvaluation(
            eval_scene=s.scene.eval_scene,
            within_scene=bool(s.scene.within_scene),
            metrics=s.model.metrics,
            n_test=int(len(s.model.arrays["ids"])),
            band_hz=float(s.scene.datamodule.bands[0].frequency_hz),
            scene_index=int(s.scene.datamodule.scene_index[0]),
            splits=s.scene.datamodule.split_summary(),
            timing=headline_timing if i == 0 else s.model.timing,
            baselines={b.method: b.figures() for b in s.baselines},
        )
        for i, s in enumerate(scenes)
    ]


def write_run(cfg: DictConfig, built: BuiltRun, record: RunRecord, scenes: list[SceneTest]) -> None:
    """The one writer of a run's files: the predictions and figure its record names, the samples, then
    results.json (atomically, last: a folder with results.json holds a finished run)."""
    out, first = built.output_dir, scenes[0]
    if record.predictions:
        atomic_write_npz(out / record.predictions, **{k: first.model.arrays[k] for k in ("pred", "target", "ids")})
    if record.per_spectrum:
        write_per_spectrum(out / record.per_spectrum, per_spectrum_rows(record.method, scenes))
    if record.figure:
        a = first.model.arrays
        title = f"{record.method} on {record.eval_scene}"
        fig = plot_spectra_grid(a["pred"], a["target"], a["ids"], out / record.figure, title, int(cfg.plot_count))
        for lg in built.loggers:
            if hasattr(lg, "log_image"):
                lg.log_image(key="test/spectra", images=[str(fig)])
    n = int(cfg.get("save_samples") or 0)
    if n > 0:
        for s in scenes:
            save_samples(out, s.scene.eval_scene, record.method, s.model.arrays, n)
            for b in s.baselines:
                save_samples(out, s.scene.eval_scene, b.method, b.arrays, n)
    atomic_write_json(out / RESULTS_FILE, record.to_json())


def save_samples(out: Path, scene: str, method: str, arrays: dict, n: int) -> Path:
    """The first ``n`` test spectra of an evaluation (lowest ids: the same positions for every method on a
    scene) as ``samples/<scene>__<method>.npz`` (``pred``, ``target``: uint8 [n, 90, 360]; ``ids``), for
    graf-report's true-vs-predicted grids."""
    order = np.argsort(np.asarray(arrays["ids"]))[:n]
    q = lambda x: np.clip(np.rint(np.asarray(x)[order] * 255.0), 0, 255).astype(np.uint8)  # noqa: E731
    path = out / "samples" / f"{scene}__{method}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_npz(path, pred=q(arrays["pred"]), target=q(arrays["target"]), ids=np.asarray(arrays["ids"])[order])
    return path


def print_summary(cfg: DictConfig, record: RunRecord, scenes: list[SceneTest], out: Path) -> None:
    """The metrics table (every test scene: the model, then its baselines), which test scenes the model was
    trained on, the regime, and where the files are."""
    rows = []
    for i, s in enumerate(scenes):
        scene = record.eval_scene if i == 0 else s.scene.eval_scene
        rows.append(
            {"method": record.method, "scene": scene, "n_test": len(s.model.arrays["ids"]), "metrics": s.model.metrics}
        )
        rows += [{"method": b.method, "scene": b.scene, "n_test": b.n_test, "metrics": b.metrics} for b in s.baselines]
    print(format_metrics_table(rows))
    if record.evaluations:  # say which test scenes the model was trained on
        print(
            "; ".join(
                f"{e.eval_scene}: {'within-scene (trained on it)' if e.within_scene else 'zero-shot'}"
                for e in record.evaluations
            )
        )
    if record.regime:
        print(f"regime: {record.regime}")
    print(f"results: {out / RESULTS_FILE}")
    if record.figure:
        print(f"figure: {out / record.figure}")


def format_metrics_table(rows: list[dict]) -> str:
    """A plain-text table of the four test metrics (and the validation PSNR), one row per results dict."""
    head = (
        f"{'method':<22}{'scene':<16}{'n_test':>7}{'MSE':>10}{'PSNR':>9}{'SSIM':>8}{'LPIPS':>8}"
        f"{'val PSNR':>10}{'reliance dB':>13}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        m = r["metrics"]

        def f(key, spec, m=m):
            v = m.get(key)
            width = spec.split(".")[0]
            return format(v, spec) if v is not None and not math.isnan(v) else format("n/a", f">{width}")

        lines.append(
            f"{r['method']:<22}{r['scene']:<16}{r['n_test']:>7}{f('test/mse', '10.4f')}"
            f"{f('test/psnr', '9.2f')}{f('test/ssim', '8.3f')}{f('test/lpips', '8.3f')}"
            f"{f('val/psnr', '10.2f')}{f('test/reliance_db', '13.2f')}"
        )
    return "\n".join(lines)


def set_aside_finished(out: Path, reads: list) -> Path | None:
    """A new run in a folder that holds a finished run's results.json: move that run's files (:data:`RUN_FILES`;
    its checkpoints stay when this run reads one of them, ``reads``) into ``replaced_<when it finished>/`` and say
    so, so that the new run, interrupted, does not leave the old record beside its own config (Hydra has already
    rewritten ``.hydra/``).  Returns that folder (None: nothing to move)."""
    old = out / RESULTS_FILE
    if not old.is_file() or rank_zero_only.rank != 0:
        return None
    stamp = datetime.fromtimestamp(old.stat().st_mtime).strftime("%Y-%m-%d_%H-%M-%S")
    dest, k = out / f"replaced_{stamp}", 1
    while dest.exists():
        dest, k = out / f"replaced_{stamp}_{k}", k + 1
    dest.mkdir()
    ckpts = (out / "checkpoints").resolve()
    keep = {"checkpoints"} if any(p and ckpts in Path(str(p)).resolve().parents for p in reads) else set()
    for name in RUN_FILES:
        if (out / name).exists() and name not in keep:
            (out / name).rename(dest / (REPLACED_RESULTS if name == RESULTS_FILE else name))
    log.warning("%s held a finished run: its files are moved to %s (results.json as %s)", out, dest, REPLACED_RESULTS)
    return dest
