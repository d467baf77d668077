"""After the search: the study's files (:mod:`graf.sweeper.outputs`) and the chosen configuration tested once, the
only job of a search that sees the test split (``best/best.json``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from hydra.core.utils import JobStatus

from graf.io import atomic_write_json
from graf.search.objectives import metrics_mean
from graf.search.search_space import SearchSpace
from graf.sweeper.outputs import best_trials, write_outputs
from graf.sweeper.trials import OUTPUT, quote

log = logging.getLogger("graf")


def finish(study, ctx: dict, launch, *, plots: bool, test_best: bool, test_overrides: list[str], threads: str) -> None:
    """The outputs written, and the chosen configuration tested once (``best/best.json``), unless it was: its job
    started by ``launch(overrides, job_idx)`` with ``test_overrides`` and ``threads`` (the torch threads'
    override)."""
    out = ctx["sweep_dir"]
    space: SearchSpace = ctx["space"]
    write_outputs(study, out, space, ctx["names"], plots=plots)
    best = best_trials(study)
    if not best or not test_best:
        return
    chosen = best[0]
    record = out / "best" / "best.json"
    before = json.loads(record.read_text()) if record.is_file() else {}
    if before.get("trial") == chosen.number:
        log.info("the chosen trial %d was tested before: %s", chosen.number, record)
        if "metrics@mean" not in before and (means := metrics_mean(before.get("evaluations", []))):
            before["metrics@mean"] = means  # a record from before the means were written: from its evaluations
            atomic_write_json(record, before)
        return
    overrides = space.overrides(chosen.params) + list(test_overrides) + ["hydra.sweep.subdir=best", "validate=true"]
    ckpt = Path(chosen.user_attrs.get(OUTPUT, "")) / "checkpoints" / "last.ckpt"
    if chosen.user_attrs.get(OUTPUT) and ckpt.is_file():
        overrides.append(f"ckpt_path={quote(str(ckpt))}")  # its final weights: resumed at the last step
    overrides.append(threads)
    log.info("testing the chosen configuration (trial %d) once: %s", chosen.number, " ".join(overrides))
    ret = launch(overrides, 10**6)
    result = {
        "trial": chosen.number,
        "params": chosen.params,
        "objectives": ctx["names"],
        "values": chosen.values,
        "overrides": overrides,
        "checkpoint": str(ckpt) if ckpt.is_file() else None,
    }
    _add_test_result(result, ret)
    record.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(record, result)
    shown = result.get("metrics@mean") or result.get("metrics") or {}
    log.info(
        "chosen configuration: trial %d, %s; objective %s; validation PSNR %s, test PSNR %s%s",
        chosen.number,
        chosen.params,
        chosen.values,
        shown.get("val/psnr"),
        shown.get("test/psnr"),
        " (means over the evaluated scenes)" if "metrics@mean" in result else "",
    )


def _add_test_result(result: dict, ret) -> None:
    """The chosen configuration's test job into its record: its figures (and their means over the evaluated
    scenes), or its error."""
    if ret.status != JobStatus.COMPLETED:
        result["error"] = f"{type(ret._return_value).__name__}: {ret._return_value}"
        log.error("testing the chosen configuration failed: %s", result["error"])
        return
    res = Path(str(ret.hydra_cfg.hydra.runtime.output_dir)) / "results.json"
    if res.is_file():
        r = json.loads(res.read_text())
        result["metrics"] = r.get("metrics")
        result["evaluations"] = [
            {"eval_scene": e["eval_scene"], "metrics": e["metrics"]} for e in r.get("evaluations", [])
        ]
        result["results"] = str(res)
        if means := metrics_mean(result["evaluations"]):
            result["metrics@mean"] = means
