"""What a finished search leaves in its folder (written atomically, again after every resumed run):

- ``trials.csv``: one row per trial: number, state, the objective values (COMPLETE trials only), the
  parameters, wall seconds, start time, the last intermediate validation value and its step (what pruning saw), and
  why a trial failed, was interrupted, re-queued, duplicated or dropped;
- ``best_params.json`` and ``best_overrides.txt`` (the chosen trial's overrides, one per line, as one run
  that trains, validates and tests it: ``xargs graf-train < best_overrides.txt``); for two objectives the chosen trial
  is the Pareto-front trial
  best in the first objective, and ``pareto.json`` lists the whole front;
- figures (PNG): ``optimization_history.png``, ``param_importances.png`` (PED-ANOVA: Optuna's evaluator
  that needs no scikit-learn), ``intermediate_values.png`` (the validation curves pruning saw), and
  ``pareto_front.png`` for two objectives.
"""

from __future__ import annotations

import csv
import io
import logging
import warnings
from pathlib import Path

import optuna
from optuna.trial import FrozenTrial, TrialState

from graf.io import atomic_write_json, atomic_write_text
from graf.search.search_space import SearchSpace

log = logging.getLogger("graf")


def best_trials(study: optuna.Study) -> list[FrozenTrial]:
    """The chosen trial first: the best COMPLETE trial; for several objectives the Pareto front sorted by
    the first objective (best first)."""
    complete = [
        t
        for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        if "graf.duplicate_of" not in t.user_attrs
    ]
    if not complete:
        return []
    if len(study.directions) == 1:
        return [study.best_trial]
    sign = -1.0 if study.directions[0] == optuna.study.StudyDirection.MAXIMIZE else 1.0
    return sorted(study.best_trials, key=lambda t: sign * t.values[0])


def _value_columns(names: list[str]) -> list[str]:
    return [f"value {n}" for n in names]


def trials_table(study: optuna.Study, names: list[str]) -> tuple[list[str], list[dict]]:
    params = sorted({k for t in study.trials for k in t.params})
    front = {t.number for t in best_trials(study)} if len(study.directions) > 1 else set()
    cols = (
        ["number", "state"]
        + _value_columns(names)
        + [f"param {p}" for p in params]
        + [
            "wall_s",
            "datetime_start",
            "last_intermediate_step",
            "last_intermediate_value",
            "pareto",
            "duplicate_of",
            "requeued_from",
            "interrupted",
            "surplus",
            "error",
            "output_dir",
        ]
    )
    rows = []
    for t in study.trials:
        a = t.user_attrs
        row = {
            "number": t.number,
            "state": t.state.name,
            "wall_s": a.get("graf.wall_s"),
            "datetime_start": t.datetime_start.isoformat(timespec="seconds") if t.datetime_start else None,
            "pareto": t.number in front if front else None,
            "duplicate_of": a.get("graf.duplicate_of"),
            "requeued_from": a.get("graf.requeued_from"),
            "interrupted": a.get("graf.interrupted"),
            "surplus": a.get("graf.surplus"),
            "error": a.get("graf.error"),
            "output_dir": a.get("graf.output_dir"),
        }
        # a pruned trial has no objective value (Optuna stores its last intermediate value there): that
        # value and its step go to their own columns
        values = t.values if t.state == TrialState.COMPLETE else None
        for c, v in zip(_value_columns(names), values or [None] * len(names)):
            row[c] = v
        if t.intermediate_values:
            step = max(t.intermediate_values)
            row["last_intermediate_step"], row["last_intermediate_value"] = step, t.intermediate_values[step]
        for p in params:
            row[f"param {p}"] = t.params.get(p)
        rows.append(row)
    return cols, rows


def rerun_overrides(space: SearchSpace, params: dict) -> list[str]:
    """The chosen configuration as a single run (not a new search): the search's own settings and the
    parameters, ``hydra.mode=RUN``, and ``test=true`` (it is validated and tested)."""
    return space.overrides(params) + ["hydra.mode=RUN", "test=true"]


def write_outputs(study: optuna.Study, out: Path, space: SearchSpace, names: list[str], plots: bool = True) -> None:
    cols, rows = trials_table(study, names)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols)
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else v) for k, v in r.items()})
    atomic_write_text(out / "trials.csv", buf.getvalue())
    best = best_trials(study)
    states = {s.name: sum(1 for t in study.trials if t.state == s) for s in TrialState}
    summary = {
        "study": study.study_name,
        "objectives": names,
        "directions": [d.name.lower() for d in study.directions],
        "trials": {k: v for k, v in states.items() if v},
        "search_space": space.describe(),
    }
    if best:
        chosen = best[0]
        summary.update(
            trial=chosen.number, values=chosen.values, params=chosen.params, overrides=space.overrides(chosen.params)
        )
        atomic_write_text(out / "best_overrides.txt", "\n".join(rerun_overrides(space, chosen.params)) + "\n")
        if len(study.directions) > 1:
            atomic_write_json(
                out / "pareto.json",
                [
                    {"trial": t.number, "values": t.values, "params": t.params, "overrides": space.overrides(t.params)}
                    for t in best
                ],
            )
    atomic_write_json(out / "best_params.json", summary)
    if plots:
        write_figures(study, out, names)


def write_figures(study: optuna.Study, out: Path, names: list[str]) -> list[str]:
    # lazy: pyplot and Optuna's plotting take a second to import, and only the figures (plots=true) need them
    import matplotlib

    matplotlib.use("Agg")
    from optuna.visualization import matplotlib as ovm

    from graf.plotting import save_figure

    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    target = (lambda t: t.values[0]) if len(study.directions) > 1 else None
    jobs = [("optimization_history", lambda: ovm.plot_optimization_history(study, target=target, target_name=names[0]))]
    if len(complete) >= 2 and study.trials and study.trials[0].distributions:
        jobs.append(
            (
                "param_importances",
                lambda: ovm.plot_param_importances(
                    study,
                    evaluator=optuna.importance.PedAnovaImportanceEvaluator(),
                    target=target,
                    target_name=names[0],
                ),
            )
        )
    if any(t.intermediate_values for t in study.trials) and len(study.directions) == 1:
        jobs.append(("intermediate_values", lambda: ovm.plot_intermediate_values(study)))
    if len(study.directions) == 2:
        jobs.append(("pareto_front", lambda: ovm.plot_pareto_front(study, target_names=names)))
    written = []
    for name, make in jobs:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ax = make()
            fig = ax.figure if hasattr(ax, "figure") else ax.flat[0].figure
            fig.set_size_inches(8, 5)
            fig.tight_layout()
            save_figure(fig, out / f"{name}.png", dpi=110)
            written.append(f"{name}.png")
        except Exception as exc:  # a figure Optuna cannot draw for this study (e.g. one distinct value)
            log.warning("figure %s not drawn: %s: %s", name, type(exc).__name__, exc)
    return written
