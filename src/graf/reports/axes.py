"""The settings a study may vary (its axes), declared once: graf-report's tables nest their blocks in this order, its
intervals pair the spectra of one cell (one value of every axis), the claims ledger reads the cells by these names.

An axis reads its value from a job's ``results.json`` (:attr:`Axis.of_job`) or from one of the job's evaluations
(:attr:`Axis.of_evaluation`: a test scene, a test band).  Adding a study axis is one entry of :data:`AXES`
(docs/extending.md, "Add a study axis"); the report, the intervals and the figures follow.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from graf.metrics.names import too_late
from graf.plugins import call_registered


def band_label(hz) -> str:
    """``2.412 GHz`` or ``915 MHz`` for a frequency in Hz; "" for None."""
    if hz is None:
        return ""
    hz = float(hz)
    return f"{hz / 1e9:g} GHz" if hz >= 1e9 else f"{hz / 1e6:g} MHz"


@dataclass(frozen=True)
class Axis:
    """One setting a study may vary.

    name: the column's name in the tables, intervals and ledger.
    of_job: ``results.json -> value`` shared by every row of a job; or
    of_evaluation: ``(results.json, evaluation) -> value`` per test scene (an evaluation of the job).
    untrained: the value a baseline's row takes when the axis describes training (a baseline is not trained:
        ``-``); None when a baseline shares the job's value.
    """

    name: str
    of_job: Callable[[dict], Any] | None = None
    of_evaluation: Callable[[dict, dict], Any] | None = None
    untrained: str | None = None

    def job_value(self, result: dict) -> Any:
        """The axis's value for a job (``of_job``); a plugin's reader that raises is one line naming the axis and
        its plugin module (:func:`graf.plugins.call_registered`)."""
        return call_registered(f"study axis {self.name!r}", self.of_job, result)

    def evaluation_value(self, result: dict, evaluation: dict) -> Any:
        """The axis's value for one evaluation of a job (``of_evaluation``), as :meth:`job_value`."""
        return call_registered(f"study axis {self.name!r}", self.of_evaluation, result, evaluation)

    def value(self, result: dict, evaluation: dict) -> Any:
        return self.evaluation_value(result, evaluation) if self.of_evaluation else self.job_value(result)


def trained_on(result: dict) -> tuple[list[str], list[float]]:
    """The scenes a job's model was trained on and their bands (Hz): a fine-tuning run's base model's."""
    ft = result.get("finetune")
    if ft and ft.get("base_scenes"):
        trained = sorted(ft["base_scenes"], key=lambda n: ft["base_scenes"][n]["index"])
        train_hz = sorted({float(v["band_hz"]) for v in ft["base_scenes"].values() if v.get("band_hz")})
        return trained, train_hz
    return (
        list(result.get("train_scenes") or [result.get("scene")]),
        sorted(set(result.get("train_bands_hz") or [result.get("band_hz")])),
    )


def _ft_label(ft: dict | None) -> str:
    if not ft:
        return "-"
    if ft.get("mode") == "zero-shot":
        return "zero-shot"
    return f"f{round(100 * float(ft.get('fraction') or 1.0)):02d}"


def measured_fraction(result: dict) -> float | None:
    f = (result.get("splits") or {}).get("measured_fraction")
    return None if f is None else float(f)


def finetune_label(result: dict) -> str:
    """A fine-tuning run's fraction (``f20``, ``zero-shot``), or a from-scratch run's measured fraction (the
    density study's survey), or ``-``."""
    ft = result.get("finetune")
    if ft or measured_fraction(result) is None:
        return _ft_label(ft)
    return f"f{round(100 * measured_fraction(result)):02d}"


AXES: tuple[Axis, ...] = (
    Axis("trained_on", of_job=lambda r: "+".join(trained_on(r)[0]), untrained="-"),
    Axis("train_band", of_job=lambda r: " + ".join(band_label(h) for h in trained_on(r)[1]), untrained="-"),
    Axis("finetune", of_job=finetune_label),
    Axis("L", of_job=lambda r: ((r.get("config") or {}).get("neighbors") or {}).get("L")),
    # the neighbour-distance study's axis: candidates closer than this many wavelengths are left out, at training
    # and at test (neighbors.exclude_within), for the model and the baselines tested beside it alike
    Axis("exclude_within", of_job=lambda r: ((r.get("config") or {}).get("neighbors") or {}).get("exclude_within")),
    Axis("eval_scene", of_evaluation=lambda r, ev: ev["eval_scene"]),
    Axis("eval_band", of_evaluation=lambda r, ev: band_label(ev.get("band_hz"))),
)
AXIS_NAMES = tuple(a.name for a in AXES)


def register(axis: Axis, after: str | None = None) -> Axis:
    """Add a study axis (docs/extending.md, "Add a study axis"), nested after the axis ``after`` in the tables
    (default: after the job axes, before the test scene); graf-report's tables, its intervals' cells and the
    claims ledger read it from then on.  Call it in a plugin (``GRAF_PLUGINS``, :mod:`graf.plugins`), before any
    report module is imported."""
    global AXES, AXIS_NAMES
    if axis.name in AXIS_NAMES:
        raise ValueError(f"study axis {axis.name!r} is declared already")
    too_late([m for m in ("graf.reports.rows", "graf.reports.intervals") if m in sys.modules], f"axis {axis.name!r}")
    if (axis.of_job is None) == (axis.of_evaluation is None):
        raise ValueError(f"study axis {axis.name!r}: give of_job or of_evaluation (one of the two)")
    names = list(AXIS_NAMES)
    at = names.index(after) + 1 if after else names.index("eval_scene")
    AXES = (*AXES[:at], axis, *AXES[at:])
    AXIS_NAMES = tuple(a.name for a in AXES)
    return axis
