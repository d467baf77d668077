"""The figures every evaluation reports (``results.json``'s ``metrics``), declared once, below everything that
writes or reads them: the metric collections (:func:`graf.metrics.spectrum_metrics`), the pipeline, the records,
the reports and their figures, the sweeps' objectives.

:data:`REGISTRY` holds each per-spectrum metric's name, label, unit, direction and number format; a metric
collection with a name not registered here refuses to be made (:func:`check_metric_names`), and every registered
figure a run computes reaches ``results.json``, the per-spectrum records and the report's figures.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass

AGGREGATES = ("mean",)  # how a split's figure comes from the per-spectrum values (empty targets left out)


@dataclass(frozen=True)
class Metric:
    """A per-spectrum figure: ``name`` (``test/<name>``), its ``label`` in tables and figures, ``unit`` (or ""),
    whether higher is better, its number format, how it is computed per spectrum and how a split's figure
    aggregates those values.

    per_spectrum: ``(pred [N, H, W], target [N, H, W]) -> [N]`` (values in [0, 1]); or
    factory: a dotted path to the torchmetrics class that computes it (the built-in four, with their own
        settings: PSNR's data range, LPIPS's weights); one of the two.
    aggregate: ``mean`` over the split's non-empty spectra (the only one so far).
    on_curves: drawn and tabled by graf-curves (MSE is not: PSNR shows it on a log scale)."""

    name: str
    label: str
    unit: str
    higher_is_better: bool
    fmt: str
    per_spectrum: Callable | None = None
    factory: str | None = None
    aggregate: str = "mean"
    on_curves: bool = True

    def __post_init__(self):
        if (self.per_spectrum is None) == (self.factory is None):
            raise ValueError(f"metric {self.name!r}: give per_spectrum or factory (one of the two)")
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"metric {self.name!r}: aggregate must be one of {AGGREGATES}, got {self.aggregate!r}")

    @property
    def difference_fmt(self) -> str:
        """The number format of a difference of this metric: ``fmt``, signed (``{:+.2f}``)."""
        return self.fmt.replace("{:", "{:+", 1)

    def axis_label(self, split: str = "test") -> str:
        """``test PSNR (dB), higher is better``."""
        unit = f" ({self.unit})" if self.unit else ""
        return f"{split} {self.label}{unit}, {'higher' if self.higher_is_better else 'lower'} is better"


_CLASSES = "graf.metrics.spectrum_metrics"
REGISTRY: dict[str, Metric] = {
    m.name: m
    for m in (
        Metric("mse", "MSE", "", False, "{:.4f}", factory=f"{_CLASSES}.SpectrumMSE", on_curves=False),
        Metric("psnr", "PSNR", "dB", True, "{:.2f}", factory=f"{_CLASSES}.SpectrumPSNR"),
        Metric("ssim", "SSIM", "", True, "{:.3f}", factory=f"{_CLASSES}.SpectrumSSIM"),
        Metric("lpips", "LPIPS", "", False, "{:.3f}", factory=f"{_CLASSES}.SpectrumLPIPS"),
    )
}
# <split>/n_empty: how many targets were empty (no path: every pixel 0), left out of every mean above
# (graf.metrics.spectrum_metrics.empty_targets)
COUNT_NAMES = ("n_empty",)
# <split>/psnr_swapped: PSNR with every target's neighbors replaced by another target's; <split>/reliance_db:
# <split>/psnr minus it (how much a method reads its neighbors; None for a method that takes none)
RELIANCE_NAMES = ("psnr_swapped", "reliance_db")


def _derived() -> None:
    """The names every reader takes from :data:`REGISTRY` (module attributes, kept in step by :func:`register`)."""
    global METRIC_NAMES, EVAL_METRICS
    METRIC_NAMES = tuple(REGISTRY)
    EVAL_METRICS = tuple(f"{s}/{m}" for s in ("val", "test") for m in (*METRIC_NAMES, *COUNT_NAMES)) + tuple(
        f"{s}/{m}" for s in ("val", "test") for m in RELIANCE_NAMES
    )


METRIC_NAMES: tuple[str, ...] = ()
EVAL_METRICS: tuple[str, ...] = ()
_derived()


# modules that copy the registry when they are imported: a metric registered after them would not reach them
READERS = ("graf.callbacks", "graf.run.per_spectrum", "graf.reports.rows", "graf.reports.statistics",
           "graf.reports.intervals", "graf.reports.figures", "graf.search.objectives")  # fmt: skip


def too_late(imported: list[str], what: str) -> None:
    """Refuse a registration that modules already imported would not see (it would be silently left out)."""
    if imported:
        raise ValueError(
            f"{what} registered after {', '.join(imported)} was imported, which would not see it: register it in a "
            "plugin (GRAF_PLUGINS, imported when graf is)"
        )


def register(metric: Metric) -> Metric:
    """Add a metric to :data:`REGISTRY` (docs/extending.md, "Add a metric"): every evaluation computes it from then
    on, and it reaches ``results.json``, the per-spectrum records, graf-report's tables, intervals and figures.
    Call it where graf is imported before any run starts: in a plugin (``GRAF_PLUGINS``, :mod:`graf.plugins`)."""
    if metric.name in REGISTRY or metric.name in COUNT_NAMES + RELIANCE_NAMES:
        raise ValueError(f"metric {metric.name!r} is registered already")
    too_late([m for m in READERS if m in sys.modules], f"metric {metric.name!r}")
    REGISTRY[metric.name] = metric
    _derived()
    return metric


def check_metric_names(names) -> None:
    """Refuse a metric collection holding a figure :data:`REGISTRY` does not declare (it would have no label,
    unit or direction in the records, reports and figures)."""
    unknown = [n for n in names if n not in REGISTRY and n not in COUNT_NAMES]
    if unknown:
        raise ValueError(
            f"metric(s) {', '.join(unknown)} not declared in graf.metrics.names.REGISTRY (known: "
            f"{', '.join((*REGISTRY, *COUNT_NAMES))}): declare each with its label, unit and direction"
        )


# The figures the choice rules compare with KNN's (a mode or budget is chosen where it leads KNN in all of them,
# docs/learning-curves.md): named here, their directions read from REGISTRY.
CHOICE_METRICS = ("psnr", "ssim", "lpips")


def curve_metrics() -> tuple[Metric, ...]:
    """The metrics graf-curves draws and tables (``on_curves``), in :data:`REGISTRY`'s order: a plugin's included."""
    return tuple(m for m in REGISTRY.values() if m.on_curves)


def choice_figures() -> tuple[tuple[str, bool], ...]:
    """``(val_<name>, higher is better)`` of :data:`CHOICE_METRICS`: a curve row's columns the choice rules read."""
    return tuple((f"val_{n}", REGISTRY[n].higher_is_better) for n in CHOICE_METRICS)


def record_order(metrics: dict) -> dict:
    """Every ``val/`` and ``test/`` figure of ``metrics`` (nothing computed is dropped): the declared ones in
    :data:`EVAL_METRICS`' order (None where not computed), then any other, sorted."""
    out = {k: metrics.get(k) for k in EVAL_METRICS}
    out.update({k: metrics[k] for k in sorted(metrics) if k not in out and k.split("/")[0] in ("val", "test")})
    return out
