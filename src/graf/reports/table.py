"""graf-table: collect results.json files (a run, a multirun folder, or several) into one table.

    graf-table runs=multirun/knn_rfid_s23/2026-11-22_16-00-00 [out=sweeps/knn_rfid_s23]

One row per run and test scene (a cross-scene run tests several: ``evaluations``), with the scenes it
was trained and tested on.  Config keys whose values differ between the runs become columns (so a sweep's
axes show up by themselves; a varying ``scene`` or ``eval_scene`` shows as the two scene columns, not as
the scenes' configs).  Writes ``table.md``, ``table.csv`` and ``results.json`` (``{"rows": [...]}``) into the
output folder (and into ``out`` when given), and prints the Markdown table.

Every multirun also gets its table without this command: :class:`SweepTable` (a Hydra callback, in
``conf/hydra/default.yaml``) rewrites ``table.md`` / ``table.csv`` / ``table.json`` in the sweep folder after
each job, so a sweep whose later job fails or is killed still leaves the table of the jobs that finished,
and the failed jobs are listed in ``failed.json`` beside it.

Baselines tested inside a run (results.json ``baselines``) become rows of their own; the model's own
settings (``model.*``) are left blank in them, and a baseline row identical to one already in the table
(the same KNN beside several models) appears once.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from pathlib import Path

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, ListConfig

from graf.app.config import output_dir, task_wrapper
from graf.errors import PREEMPTED_EXIT_CODE, ConfigError, UserError, is_preempted
from graf.io import atomic_write_bytes, atomic_write_json
from graf.metrics.names import REGISTRY

log = logging.getLogger("graf")

VALIDATION_COLUMNS = ("psnr", "ssim")  # the validation figures a table shows beside every test figure


def result_columns() -> list[tuple[str, str, str]]:
    """``(results.json key, column, format)`` of the figures a table shows, read from the metric registry when called
    (a plugin's metric included, in the registry's order): validation PSNR and SSIM, every test metric (blank where a
    run has none), the reliance."""
    val = [(f"val/{n}", f"val {REGISTRY[n].label}", REGISTRY[n].fmt) for n in VALIDATION_COLUMNS]
    test = [(f"test/{m.name}", m.label, m.fmt) for m in REGISTRY.values()]
    return [*val, *test, ("test/reliance_db", "reliance dB", "{:.2f}")]


IGNORED_PREFIXES = (
    "paths.",
    "hydra.",
    "data_root",
    "task_name",
    "logger.",
    "trainer.default_root_dir",
    "callbacks.",
    "save_predictions",
    "plot_count",
    "ckpt_path",
    # a search trial's link to its study (its number stays: trials.csv's key)
    "optuna_trial.storage",
    "optuna_trial.study_name",
    "optuna_trial.trial_id",
    "optuna_trial.pruner",
)


# config groups that hold whole scene configs keyed by scene name: one column of the names (the scenes'
# geometry, materials and tracing settings would otherwise become a hundred columns when the scene varies)
NAMED_GROUPS = ("scene", "eval_scene")


def _flat_config(config: dict) -> dict:
    """A run's config flattened to ``{dotted.key: value}``, each of NAMED_GROUPS as its scene names."""
    out = _flatten({k: v for k, v in config.items() if k not in NAMED_GROUPS})
    for g in NAMED_GROUPS:
        if isinstance(config.get(g), dict):
            out[g] = "+".join(config[g])
        elif g in config:
            out[g] = config[g]
    return out


def _flatten(d, prefix=""):
    out = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
    else:
        out[prefix[:-1]] = json.dumps(d) if isinstance(d, list) else d
    return out


# settings of the run's own model and training, which do not apply to the baselines tested beside it
BASELINE_BLANK = ("model.", "model", "trainer.", "experiment")


def _natural(path: Path) -> list:
    """Sort key so that multirun job 10 comes after job 9."""
    return [int(part) if part.isdigit() else part for part in path.parts]


# results.json files that are a collecting command's own output, not a run's (graf-table, graf-pareto)
COLLECTED = ("table", "pareto")


def read_run_result(f: Path) -> dict | None:
    """A run's ``results.json`` as a dict (a run's holds its ``metrics`` or its ``evaluations``); None for
    another command's output (a collecting command's: ``task`` in :data:`COLLECTED`, or a table's ``{"rows",
    "sources"}`` written before it said its task; or one whose config names its command, ``config.task_name``:
    graf-simulate's beside a graf-pareto sweep's runs); a :class:`ConfigError` naming the file when it is
    unreadable or holds no run's results."""
    try:
        r = json.loads(Path(f).read_text())
    except (json.JSONDecodeError, OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{f}: not a readable results.json ({exc})") from None
    if not isinstance(r, dict):
        raise ConfigError(
            f"{f}: a results.json holds one run's results as a JSON object; this one holds a {type(r).__name__}"
        )
    if r.get("task") in COLLECTED or ("rows" in r and "metrics" not in r):
        return None
    if not isinstance(r.get("metrics"), dict) and not isinstance(r.get("evaluations"), list):
        if isinstance(r.get("config"), dict) and r["config"].get("task_name"):
            return None
        raise ConfigError(f"{f}: not a run's results.json (it holds neither metrics nor evaluations)")
    return r


def collect(paths: list[str | Path]) -> list[dict]:
    """Every run's results under ``paths`` (folders searched recursively, or files); collecting commands' own
    outputs (a table written into a folder it reads) are passed over."""
    files = []
    for p in paths:
        p = Path(p)
        if p.is_file():
            files.append(p)
        elif p.is_dir():
            files.extend(sorted(p.rglob("results.json"), key=_natural))
        else:
            raise ConfigError(f"graf-table: runs={p} does not exist")
    rows = []
    for f in files:
        r = read_run_result(f)
        if r is None:
            log.info("%s: another command's output, not a run: left out", f)
            continue
        r["_file"] = str(f)
        rows.append(r)
    if not rows:
        raise ConfigError(f"graf-table: no run's results.json under {', '.join(map(str, paths))}")
    return rows


def varying_keys(rows: list[dict]) -> list[str]:
    """Config keys whose values differ between the runs.  When the runs are of different methods
    (``model._target_`` varies), the model's own settings are left out: they are not comparable across
    methods, the method column names the model, and each run's results.json holds its full config."""
    flats = [_flat_config(r.get("config", {})) for r in rows]
    keys = sorted(set().union(*flats)) if flats else []
    varying = [
        k
        for k in keys
        if not k.startswith(IGNORED_PREFIXES) and len({json.dumps(f.get(k), default=str) for f in flats}) > 1
    ]
    if "model._target_" in varying:
        varying = [k for k in varying if not k.startswith("model.")]
    return varying


def _evaluations(r: dict) -> list[dict]:
    """A run's evaluations: one per test scene (``evaluations`` of a cross-scene run; the run itself before)."""
    return r.get("evaluations") or [
        {
            "eval_scene": r.get("eval_scene") or r.get("scene"),
            "metrics": r.get("metrics", {}),
            "n_test": r.get("n_test"),
            "baselines": r.get("baselines") or {},
        }
    ]


def build_table(rows: list[dict]) -> tuple[list[str], list[list]]:
    """One row per (run, test scene) and per baseline tested beside it: the method, the scenes it was trained
    and tested on, the config keys that vary between the runs, the budget and the metrics."""
    axes = [k for k in varying_keys(rows) if k not in NAMED_GROUPS]  # the two scene columns name them
    keys = [k for k, _, _ in result_columns()]
    header = ["method", "trained on", "tested on", *axes, "parameters", "steps", "n_test"]
    header += [*[c for _, c, _ in result_columns()], "seconds"]
    body, seen = [], set()
    for r in rows:
        flat = _flat_config(r.get("config", {}))
        trained = "+".join(r.get("train_scenes") or [r.get("scene")]) if r.get("global_step") else "-"
        for i, e in enumerate(_evaluations(r)):
            m = e.get("metrics", {})
            body.append(
                [
                    r.get("method"),
                    trained,
                    e.get("eval_scene"),
                    *[flat.get(k) for k in axes],
                    r.get("trainable_parameters"),
                    r.get("global_step"),
                    e.get("n_test"),
                    *[m.get(k) for k in keys],
                    r.get("seconds") if i == 0 else None,
                ]
            )
            for name, b in (e.get("baselines") or {}).items():  # tested in the same run, same split and neighbors
                ax = [None if k.startswith(BASELINE_BLANK) else flat.get(k) for k in axes]
                key = json.dumps([name, e.get("eval_scene"), ax, b["metrics"]], default=str)
                if key in seen:
                    continue
                seen.add(key)
                body.append(
                    [
                        name,
                        "-",
                        e.get("eval_scene"),
                        *ax,
                        b.get("trainable_parameters"),
                        None,
                        e.get("n_test"),
                        *[b["metrics"].get(k) for k in keys],
                        b.get("seconds"),
                    ]
                )
    return header, body


def _fmt(v, col):
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return {c: f for _, c, f in result_columns()}.get(col, "{:.1f}" if col == "seconds" else "{:g}").format(v)
    return "" if v is None else str(v)


def to_markdown(header, body, fmt=None) -> str:
    """A Markdown table; ``fmt(value, column) -> str`` formats each cell (default: this table's)."""
    fmt = fmt or _fmt
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(fmt(v, c) for v, c in zip(row, header)) + " |" for row in body]
    return "\n".join(lines) + "\n"


def to_csv(header, body) -> str:
    """CSV text (None as an empty cell)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    w.writerows(body)
    return buf.getvalue()


@task_wrapper
def make_table(cfg: DictConfig) -> dict:
    runs = cfg.runs
    runs = list(runs) if isinstance(runs, (list, ListConfig)) else [runs]
    rows = collect(runs)
    for folder in [output_dir(cfg)] + ([Path(cfg.out)] if cfg.get("out") else []):
        payload = write_table(folder, rows, [str(r) for r in runs])
    print(to_markdown(*build_table(rows)))
    return payload


def write_table(folder: Path, rows: list[dict], sources: list[str], json_name: str = "results.json") -> dict:
    """Write ``table.md``, ``table.csv`` and the rows as JSON (``json_name``) into ``folder``, atomically.
    A sweep folder's JSON is ``table.json``: a ``results.json`` there would be read back as a run."""
    header, body = build_table(rows)
    payload = {"task": "table", "rows": [dict(zip(header, row)) for row in body], "sources": sources}
    atomic_write_bytes(folder / "table.md", to_markdown(header, body).encode())
    atomic_write_bytes(folder / "table.csv", to_csv(header, body).encode())
    atomic_write_json(folder / json_name, payload)
    return payload


class SweepTable(Callback):
    """Hydra callback: after every job of a multirun, rewrite the sweep folder's table from the results.json
    files under it (``table.md``, ``table.csv``, ``table.json``) and record failed jobs in ``failed.json``.
    Never raises: a table that cannot be written is logged, the sweep goes on."""

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs) -> None:
        if config.hydra.get("mode") != RunMode.MULTIRUN:
            return
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            pruned = type(job_return._return_value).__name__ == "TrialPruned"  # an Optuna search's pruned trial:
            if job_return.status == JobStatus.FAILED and not pruned:  # stored as PRUNED, not a failure
                failed_file = sweep_dir / "failed.json"
                failed = json.loads(failed_file.read_text()) if failed_file.exists() else []
                failed.append(
                    {
                        "job": int(config.hydra.job.num),
                        "overrides": list(config.hydra.overrides.task),
                        "error": repr(job_return._return_value),
                    }
                )
                atomic_write_json(failed_file, failed)
            files = sorted(sweep_dir.rglob("results.json"), key=_natural)
            if files:
                write_table(sweep_dir, collect(files), [str(f) for f in files], json_name="table.json")
                log.info("sweep table: %s", sweep_dir / "table.md")
        except Exception:  # a table is a convenience: never break the sweep
            log.exception("could not write the sweep table in %s", sweep_dir)
        # a job stopped by SIGTERM (a cluster pre-empting the multirun) stops the multirun: the next jobs would be
        # pre-empted too, or run on after the user asked to stop; the same command resumes (finished jobs are
        # skipped; a study's base model resumes from its checkpoint).  An Optuna search's trial is the sweeper's
        # to handle (queued again, then the search stops).
        if (
            job_return.status == JobStatus.FAILED
            and is_preempted(job_return._return_value)
            and config.get("optuna_trial") is None
        ):
            log.error(
                "job %s was pre-empted (SIGTERM): the multirun stops here; run the same command again to resume",
                config.hydra.job.num,
            )
            raise SystemExit(PREEMPTED_EXIT_CODE)


def md(header: list[str], body: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in body]
    return "\n".join(lines)


def fmt(v, f: str) -> str:
    return "-" if v is None else f.format(v)


# --- the main job's headline table (the README's, Home's and Getting started's: one generator) ---
HEADLINE = "sweeps/main_job/results.json"  # the main job's published record: the one headline table
ACCURATE = "sweeps/main_job_accurate/results.json"  # experiment=graf_rfid_s23_accurate: the accurate variant


def markers(source: str = HEADLINE) -> tuple[str, str]:
    """The README's markers around the table generated from the record ``source``."""
    return f"<!-- headline: generated from {source}; do not edit -->", "<!-- /headline -->"


HEADLINE_MARKERS = markers(HEADLINE)


def headline(record: dict, source: str = HEADLINE) -> str:
    """The main job's table (the README's, Home's and Getting started's, so the three cannot disagree): GRaF and
    each baseline tested beside it, test PSNR, SSIM, LPIPS (arrows: which way is better), reliance and validation
    PSNR, from its ``results.json`` (``source``: the record's path, named under the table)."""
    rows = [(record["method"], record["metrics"])]
    rows += [(name, b["metrics"]) for name, b in (record.get("baselines") or {}).items()]
    head = ["method", "PSNR (dB) ↑", "SSIM ↑", "LPIPS ↓", "reliance (dB)", "val PSNR (dB) ↑"]
    keys = (("test/psnr", "{:.2f}"), ("test/ssim", "{:.3f}"), ("test/lpips", "{:.3f}"),
            ("test/reliance_db", "{:.2f}"), ("val/psnr", "{:.2f}"))  # fmt: skip
    body = [[f"`{name}`", *(fmt(m.get(k), f) for k, f in keys)] for name, m in rows]
    fit = (record.get("timing") or {}).get("fit_s")
    took = f", {fit / 60:.1f} min of training" if fit else ""
    where = f"{record['scene']}, {record['n_test']} test spectra, {record['global_step']:,} training steps{took}"
    return md(head, body) + f"\n\n*{where}; generated from `{source}`.*"


def with_headline(text: str, record: dict, source: str = HEADLINE) -> str:
    """``text`` (the README) with the block between :func:`markers` of ``source`` replaced by :func:`headline`."""
    start, end = markers(source)
    if start not in text:
        raise UserError(f"no headline block ({start} ... {end}) to fill")
    before, rest = text.split(start, 1)
    if end not in rest:
        raise UserError(f"the headline block of {source} has no end marker {end}")
    _, after = rest.split(end, 1)
    return f"{before}{start}\n{headline(record, source)}\n{end}{after}"
