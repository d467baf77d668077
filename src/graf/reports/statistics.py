"""Paired comparisons with intervals: a method against a reference (KNN, KNN-DL) on the same test spectra, from
the jobs' per-spectrum records (:mod:`graf.run.per_spectrum`).

For one cell of a study (a test scene under one setting: trained on, L, fine-tuning, bands) and a metric, a
method with seeds ``s = 1..S`` has per-spectrum values ``a[s, i]`` on the test spectra ``i`` (the same fixed
subset for every method and seed: paired by spectrum id), and the reference ``b[r, i]`` (one run for KNN, its
seeds for KNN-DL).  Then

- the difference per spectrum is ``d[i] = mean_s a[s, i] - mean_r b[r, i]`` and the figure is its mean;
- the interval over spectra is the 95% BCa bootstrap of that mean (:func:`scipy.stats.bootstrap`, paired by
  resampling spectra, 9,999 resamples, seeded);
- the seeds' spread is the range of ``mean_i (a[s, i] - mean_r b[r, i])`` over the method's seeds, and the
  interval reported is the bootstrap interval *widened to include every seed's own difference* (a stated,
  conservative two-level rule: one seed's training luck cannot make a difference look settled);
- the verdict is ``ahead`` (the interval excludes 0 on the better side: higher PSNR / SSIM, lower MSE /
  LPIPS), ``behind`` (excludes 0 on the worse side) or ``level`` (the interval includes 0).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from graf.metrics.names import REGISTRY

HIGHER_IS_BETTER = {m.name: m.higher_is_better for m in REGISTRY.values()}  # every registered metric
CONFIDENCE = 0.95
RESAMPLES = 9999


class PairingError(ValueError):
    """The two sides of a comparison were not tested on the same spectra."""


def _matrix(runs: list[dict[int, float]], ids: list[int], who: str) -> np.ndarray:
    """``[runs, spectra]`` of per-spectrum values (``{id: value}`` per run) in the order ``ids``."""
    out = np.empty((len(runs), len(ids)))
    for k, run in enumerate(runs):
        missing = [i for i in ids if i not in run]
        if missing or len(run) != len(ids):
            extra = sorted(set(run) - set(ids))
            raise PairingError(
                f"{who}: run {k} was tested on other spectra than the comparison's (missing ids {missing[:5]}, "
                f"extra ids {extra[:5]}): the test subsets differ"
            )
        out[k] = [run[i] for i in ids]
    return out


def verdict(low: float, high: float, metric: str) -> str:
    """``ahead`` / ``behind`` / ``level (interval includes 0)`` for an interval of method minus reference."""
    better_up = HIGHER_IS_BETTER[metric]
    if low > 0:
        return "ahead" if better_up else "behind"
    if high < 0:
        return "behind" if better_up else "ahead"
    return "level (interval includes 0)"


def _bootstrap(d: np.ndarray, method: str, seed: int) -> tuple[float, float]:
    """The 95% bootstrap interval of the mean of ``d`` (scipy.stats.bootstrap, seeded)."""
    res = stats.bootstrap(
        (d,), np.mean, confidence_level=CONFIDENCE, n_resamples=RESAMPLES, method=method,
        random_state=np.random.default_rng(seed),
    )  # fmt: skip
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def paired_difference(
    method: list[dict[int, float]], reference: list[dict[int, float]], metric: str, seed: int = 0
) -> dict:
    """Method minus reference on the same spectra (see the module doc): ``method`` and ``reference`` are lists
    (one per seed or run) of ``{spectrum id: value}``.  Returns ``diff``, ``low``, ``high`` (the reported
    interval), ``boot_low`` / ``boot_high`` (over spectra only), ``seed_diffs`` (each seed's), ``n_spectra``,
    ``n_seeds``, ``n_reference``, ``verdict``, and ``share_ahead``: the share of spectra on which the method's
    seed-averaged value is better than the reference's (ties count as not better)."""
    if not method or not reference:
        raise PairingError("a paired difference needs at least one run of the method and of the reference")
    ids = sorted(method[0])
    if not ids:
        raise PairingError("no test spectra to compare")
    a = _matrix(method, ids, "method")
    b = _matrix(reference, ids, "reference").mean(axis=0)
    d = a.mean(axis=0) - b  # [spectra]
    seed_diffs = (a - b).mean(axis=1)
    diff = float(d.mean())
    if len(d) < 2 or float(np.ptp(d)) == 0.0:  # no spread to resample: the interval is the figure itself
        lo = hi = diff
    else:
        lo, hi = _bootstrap(d, "BCa", seed)
        if not (math.isfinite(lo) and math.isfinite(hi)):  # BCa degenerate (e.g. a single outlier): percentile
            lo, hi = _bootstrap(d, "percentile", seed)
    low, high = min(lo, float(seed_diffs.min())), max(hi, float(seed_diffs.max()))
    return {
        "diff": diff,
        "low": low,
        "high": high,
        "boot_low": lo,
        "boot_high": hi,
        "seed_diffs": [float(x) for x in seed_diffs],
        "n_spectra": len(ids),
        "n_seeds": len(method),
        "n_reference": len(reference),
        "verdict": verdict(low, high, metric),
        "share_ahead": float(np.mean(d > 0 if HIGHER_IS_BETTER[metric] else d < 0)),
    }


def summary(method: list[dict[int, float]]) -> dict:
    """Mean and median over spectra of the seed-averaged values, and the seeds' means (their spread)."""
    ids = sorted(method[0])
    a = _matrix(method, ids, "method")
    per_seed = a.mean(axis=1)
    return {
        "mean": float(a.mean()),
        "median": float(np.median(a.mean(axis=0))),
        "seed_means": [float(x) for x in per_seed],
        "seed_spread": float(np.ptp(per_seed)) if len(per_seed) > 1 else 0.0,
        "n_spectra": len(ids),
        "n_seeds": len(method),
    }
