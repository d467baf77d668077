"""What a search may optimise (``optimized_metric``: one name, or a list for a multi-objective search).

- ``val/<m>`` (``m`` in mse, psnr, ssim, lpips): the validation figure of the run's first test scene;
- ``val/<m>@mean``: the mean of that figure over all the run's test scenes (``eval_scene=[...]``: each
  scene's validation split, its neighbors from that scene's fit part; held out from its test split);
- ``cost/infer_s_per_spectrum``: seconds per predicted spectrum of the trained model (median over
  ``COST_BATCHES`` validation batches after one warm-up batch, divided by the batch size; prediction
  only, no metric).

A test metric is refused: nothing is chosen on the test split.  Each objective's direction is its metric's
(:data:`graf.metrics.names.REGISTRY`: higher or lower is better; a cost: lower), :func:`objective_direction`.
"""

from __future__ import annotations

import math
import statistics
import time

import torch

from graf.errors import ConfigError
from graf.metrics.names import METRIC_NAMES, REGISTRY

COST_BATCHES = 3
COSTS = ("cost/infer_s_per_spectrum",)


def check_objective_names(names: list[str]) -> None:
    for n in names:
        base, _, agg = str(n).partition("@")
        ok = (base.startswith("val/") and base[4:] in METRIC_NAMES and agg in ("", "mean")) or (str(n) in COSTS)
        if not ok:
            raise ConfigError(
                f"optimized_metric={n}: a search may optimise val/<{'|'.join(METRIC_NAMES)}>, "
                f"val/<metric>@mean (over the run's test scenes) or {', '.join(COSTS)}; nothing is "
                "chosen on the test split"
            )


def objective_direction(name: str) -> str:
    """``maximize`` or ``minimize``: the direction of objective ``name`` (checked by :func:`check_objective_names`),
    read from the metric registry at call time (a plugin's metric included); a cost is minimised."""
    if str(name) in COSTS:
        return "minimize"
    metric = REGISTRY[str(name).partition("@")[0].split("/", 1)[1]]
    return "maximize" if metric.higher_is_better else "minimize"


def objective_directions(names: list[str], given=None) -> list[str]:
    """One direction per objective: each one's own (:func:`objective_direction`) when ``given`` is None, else
    ``given`` (``hydra.sweeper.direction``: one value or a list), checked against them: a count that differs, a
    value other than maximize/minimize, or a direction that contradicts its metric stops with one line."""
    own = [objective_direction(n) for n in names]
    if given is None:
        return own
    given = [str(given)] if isinstance(given, str) else [str(d) for d in given]
    for d in given:
        if d not in ("maximize", "minimize"):
            raise ConfigError(f"hydra.sweeper.direction: {d!r} is not maximize or minimize")
    if len(names) != len(given):
        raise ConfigError(
            f"optimized_metric {names} has {len(names)} value(s) but hydra.sweeper.direction "
            f"has {len(given)}: give one direction per objective (or none: each objective's own)"
        )
    for n, d, o in zip(names, given, own):
        if d != o:
            better = "higher" if o == "maximize" else "lower"
            raise ConfigError(
                f"hydra.sweeper.direction {d} for {n} contradicts the metric ({better} is better: {o}); leave "
                "direction out and each objective takes its own"
            )
    return given


def inference_seconds_per_spectrum(model, dm, batches: int = COST_BATCHES) -> float:
    """Median seconds per spectrum of ``model.predict_spectra`` on validation batches (one warm-up first)."""
    model.eval()
    times = []
    with torch.no_grad():
        for i, batch in enumerate(dm.val_dataloader()):
            if i > batches:
                break
            batch = {k: v.to(model.device) if torch.is_tensor(v) else v for k, v in batch.items()}
            if model.device.type == "cuda":
                torch.cuda.synchronize(model.device)
            t0 = time.perf_counter()
            model.predict_spectra(batch)
            if model.device.type == "cuda":
                torch.cuda.synchronize(model.device)
            if i > 0:
                times.append((time.perf_counter() - t0) / int(batch["tgt_pos"].shape[0]))
    if not times:
        raise ConfigError(
            "cost/infer_s_per_spectrum needs at least 2 validation batches (one to warm up); "
            "lower data.batch_size or raise data.val_fraction"
        )
    return float(statistics.median(times))


def objective_values(
    names: list[str], metrics: dict, scene_metrics: list[dict] | None = None, model=None, datamodule=None
) -> list[float]:
    """The values of ``names`` for a finished run: ``metrics``, its headline figures; ``scene_metrics``, every
    test scene's (default: the headline's alone); ``model`` and ``datamodule`` (its first test scene's), for the
    costs.  A missing figure is NaN."""
    check_objective_names(names)
    out = []
    for n in names:
        base, _, agg = str(n).partition("@")
        if n in COSTS:
            ok = model is not None and datamodule is not None
            out.append(inference_seconds_per_spectrum(model, datamodule) if ok else math.nan)
        elif agg == "mean":
            vals = [m.get(base) for m in (scene_metrics or [metrics])]
            vals = [float(v) if v is not None else math.nan for v in vals]
            out.append(sum(vals) / len(vals) if vals else math.nan)
        else:
            v = metrics.get(base)
            out.append(float(v) if v is not None else math.nan)
    return out


def metrics_mean(evaluations: list[dict]) -> dict[str, float] | None:
    """Every metric of a run averaged over its evaluated scenes, as ``@mean`` averages one (``best.json``'s
    ``metrics@mean``): only the metrics every scene has; None for fewer than two scenes."""
    evals = [e["metrics"] for e in evaluations]
    if len(evals) < 2:
        return None
    return {k: float(statistics.fmean(m[k] for m in evals)) for k in evals[0] if all(k in m for m in evals)}
