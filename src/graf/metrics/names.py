"""The figures every evaluation reports (``results.json``'s ``metrics``), declared once, below everything that
writes or reads them: the metric collections (:func:`graf.metrics.spectrum_metrics`), the pipeline, the records,
the reports and their figures, the sweeps' objectives.

:data:`REGISTRY` holds each per-spectrum metric's name, label, unit, direction and number format; a metric
collection with a name not registered here refuses to be made (:func:`check_metric_names`), and every registered
figure a run computes reaches ``results.json``, the per-spectrum records and the report's figures.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Metric:
    """A per-spectrum figure: ``name`` (``test/<name>``), its ``label`` in tables and figures, ``unit`` (or ""),
    whether higher is better, and its number format."""

    name: str
    label: str
    unit: str
    higher_is_better: bool
    fmt: str

    def axis_label(self, split: str = "test") -> str:
        """``test PSNR (dB), higher is better``."""
        unit = f" ({self.unit})" if self.unit else ""
        return f"{split} {self.label}{unit}, {'higher' if self.higher_is_better else 'lower'} is better"


REGISTRY: dict[str, Metric] = {
    m.name: m
    for m in (
        Metric("mse", "MSE", "", False, "{:.4f}"),
        Metric("psnr", "PSNR", "dB", True, "{:.2f}"),
        Metric("ssim", "SSIM", "", True, "{:.3f}"),
        Metric("lpips", "LPIPS", "", False, "{:.3f}"),
    )
}
METRIC_NAMES = tuple(REGISTRY)
# <split>/n_empty: how many targets were empty (no path: every pixel 0), left out of every mean above
# (graf.metrics.spectrum_metrics.empty_targets)
COUNT_NAMES = ("n_empty",)
# <split>/psnr_swapped: PSNR with every target's neighbors replaced by another target's; <split>/reliance_db:
# <split>/psnr minus it (how much a method reads its neighbors; None for a method that takes none)
RELIANCE_NAMES = ("psnr_swapped", "reliance_db")
EVAL_METRICS = tuple(f"{s}/{m}" for s in ("val", "test") for m in (*METRIC_NAMES, *COUNT_NAMES)) + tuple(
    f"{s}/{m}" for s in ("val", "test") for m in RELIANCE_NAMES
)


def check_metric_names(names) -> None:
    """Refuse a metric collection holding a figure :data:`REGISTRY` does not declare (it would have no label,
    unit or direction in the records, reports and figures)."""
    unknown = [n for n in names if n not in REGISTRY and n not in COUNT_NAMES]
    if unknown:
        raise ValueError(
            f"metric(s) {', '.join(unknown)} not declared in graf.metrics.names.REGISTRY (known: "
            f"{', '.join((*REGISTRY, *COUNT_NAMES))}): declare each with its label, unit and direction"
        )


def record_order(metrics: dict) -> dict:
    """Every ``val/`` and ``test/`` figure of ``metrics`` (nothing computed is dropped): the declared ones in
    :data:`EVAL_METRICS`' order (None where not computed), then any other, sorted."""
    out = {k: metrics.get(k) for k in EVAL_METRICS}
    out.update({k: metrics[k] for k in sorted(metrics) if k not in out and k.split("/")[0] in ("val", "test")})
    return out
