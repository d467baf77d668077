"""graf-curves: learning curves on validation data (``conf/curves.yaml``).

    graf-curves out=sweeps/learning_curves [until=1000] ['only_regimes=[rfid_sparse]'] ['only_methods=[ray]']

For each regime and method, one training trajectory (``each_point: resume``, the default): a ``graf-train`` run per
evaluation step of ``steps`` (up to the regime's ``max_steps``), into ``<out>/<regime>/<method>/step_<N>/``, each
resuming the previous step's ``checkpoints/last.ckpt`` with a longer ``trainer.max_steps`` (once the next point is
done, a point's checkpoint is removed unless ``keep_checkpoints=true``: a curve keeps its newest, which a later run
resumes; the schedule's length is the regime's budget at every point, so the points lie on one run). A regime with
``each_point: own_run`` trains each point from scratch instead, its schedule over the point's own steps: the recipe a
study with that budget runs, so a budget chosen on such a curve is the one that was validated. Every run validates
(``test=false``: the curves choose nothing on test data) and measures validation reliance. KNN, which trains nothing,
is validated once per regime into ``<out>/<regime>/knn/``. A point whose results.json exists is skipped, so the
command resumes where it stopped, and ``until`` runs the curve only so far; a failed run is recorded in
``failed.json`` and ends that method's curve (later points need its checkpoint) while the others go on. A SIGTERM
stops the run in progress with its state saved (graf-train's ``preempted.json``) and the command with exit code 143;
the next invocation resumes that point from its own checkpoint (the stopped attempt's training seconds still count in
``fit_s``). Each run also saves its checkpoint every ``checkpoint_every`` steps, so a run killed outright (SIGKILL, a
lost machine) resumes from its newest one, and the seconds its saved steps cost (written in the checkpoint by
``graf.callbacks.AttemptClock``) count too; the steps after it are trained again.

After every run: ``curves.csv``, ``curves.md``, ``results.json`` (``rows``: regime, method, step, val_psnr,
val_ssim, val_lpips, val_reliance_db, fit_s (cumulative wall seconds of training), s_per_step (the last
attempt's), device (each attempt's, in order: ``NVIDIA H200 + cpu`` for a point resumed on a CPU); and ``knn``:
each regime's KNN figures) and ``curves.png`` (PSNR, SSIM and LPIPS against steps on a log axis, one row per
regime, KNN as a dashed line).  A cross-scene regime's figures are the means over its validation scenes.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from graf.app.config import output_dir, task_wrapper
from graf.app.launch import command
from graf.errors import Preempted
from graf.io import atomic_write_json
from graf.metrics.names import curve_metrics
from graf.run.evaluation import short_device
from graf.studies.curves_outputs import write_outputs
from graf.studies.curves_settings import check_settings, own_runs, subset
from graf.studies.runner import run_command

log = logging.getLogger("graf")

PREEMPTED_RUNS = "preempted_runs.json"  # a point's pre-empted attempts (their preempted.json records)
TRAIN = command("graf-train")  # graf-train in a subprocess (graf.app.launch)
QUIET = ["logger=none", "plot_count=0", "baselines=null", "test=false", "trainer.enable_progress_bar=false"]


def val_figures(result: dict) -> dict:
    """``{val/<metric>, val/reliance_db}`` of a run, for each metric on the curves (:func:`curve_metrics`, a
    plugin's included): its own, or the mean over its evaluations (a cross-scene run validates each scene on its
    own)."""
    keys = (*(f"val/{m.name}" for m in curve_metrics()), "val/reliance_db")
    evals = result.get("evaluations") or [{"metrics": result.get("metrics") or {}}]
    out = {}
    for k in keys:
        v = [e["metrics"].get(k) for e in evals if (e.get("metrics") or {}).get(k) is not None]
        out[k] = float(np.mean(v)) if v else None
    return out


def points(cfg: DictConfig, regime: DictConfig, until: bool = True) -> list[int]:
    """The regime's evaluation steps (its own ``steps`` where it has them, else ``cfg.steps``; its budget
    included); with ``until``, only those at or below ``cfg.until``."""
    own = regime.get("steps") or cfg.steps
    steps = sorted({int(s) for s in own if int(s) <= int(regime.max_steps)} | {int(regime.max_steps)})
    return [s for s in steps if not until or cfg.get("until") is None or s <= int(cfg.until)]


def collect(out: Path, cfg: DictConfig) -> tuple[list[dict], dict]:
    """Every finished point on disk of every configured regime and method, whatever this invocation's
    ``only_regimes``, ``only_methods`` and ``until`` (a run of a subset must not drop the others' rows)."""
    rows, knn = [], {}
    for rname, regime in cfg.regimes.items():
        f = out / rname / "knn" / "results.json"
        if f.exists():
            knn[rname] = val_figures(json.loads(f.read_text()))
        own = own_runs(regime, rname)
        for mname in cfg.methods:
            fit_s = 0.0
            for step in points(cfg, regime, until=False):
                f = out / rname / mname / f"step_{step}" / "results.json"
                if not f.exists():
                    if own:  # runs of their own: a later point does not need this one
                        continue
                    break
                if own:  # a point's seconds are its own run's, not the curve's so far
                    fit_s = 0.0
                r = json.loads(f.read_text())
                t = r.get("timing") or {}
                # an attempt whose seconds are unknown (killed with a checkpoint older than AttemptClock) makes the
                # cumulative seconds unknown from there on: n/a, not an undercount
                parts = [t.get("fit_s"), *(p.get("fit_s") for p in preempted_runs(f.parent))]
                fit_s = None if fit_s is None or any(x is None for x in parts) else fit_s + sum(map(float, parts))
                v = val_figures(r)
                rows.append(
                    {
                        "regime": rname,
                        "method": mname,
                        "step": int(r.get("global_step", step)),
                        **{k.replace("/", "_", 1): x for k, x in v.items()},
                        "fit_s": None if fit_s is None else round(fit_s, 1),
                        "s_per_step": t.get("fit_s_per_step"),
                        # where the point's training attempts ran, in order (seconds differ by orders of magnitude)
                        "device": attempt_devices(preempted_runs(f.parent), r.get("device")),
                    }
                )
    return rows, knn


def preempted_runs(folder: Path) -> list[dict]:
    """The ``preempted.json`` records of a point's earlier, pre-empted attempts (their training seconds count)."""
    f = folder / PREEMPTED_RUNS
    return json.loads(f.read_text()) if f.exists() else []


def resume_from(folder: Path, prev: Path | None) -> Path | None:
    """The checkpoint a point resumes from: its own pre-empted attempt's (``preempted.json``, whose record moves to
    ``preempted_runs.json``), else the previous point's ``last.ckpt`` (None: the curve's first point)."""
    f = folder / "preempted.json"
    if f.exists():
        record = json.loads(f.read_text())
        ckpt = _recorded_checkpoint(folder, record.get("checkpoint"))
        if ckpt is not None:
            record["checkpoint"] = str(ckpt)
            atomic_write_json(folder / PREEMPTED_RUNS, [*preempted_runs(folder), record])
            f.unlink()
            log.info("%s: resuming its pre-empted run from step %s (%s)", folder, record.get("global_step"), ckpt)
            return Path(ckpt)
        log.warning(
            "%s: the pre-empted run left no checkpoint (%s); starting the point again", folder, record.get("checkpoint")
        )
        f.unlink()
    killed = _killed_attempt(folder)
    if killed is not None:
        # a checkpoint already on record (a pre-emption's, whose resumed run was then killed before its next
        # save) is resumed from again, and its seconds are not counted twice
        if not any(r.get("global_step") == killed["global_step"] for r in preempted_runs(folder)):
            if killed["fit_s"] is None:
                log.warning(
                    "%s: the checkpoint holds no training time of its attempt; the curve's seconds become "
                    "n/a from this point",
                    killed["checkpoint"],
                )
            atomic_write_json(folder / PREEMPTED_RUNS, [*preempted_runs(folder), killed])
        log.info("%s: resuming a killed run from its checkpoint at step %d", folder, killed["global_step"])
        return Path(killed["checkpoint"])
    return None if prev is None else prev / "checkpoints" / "last.ckpt"


def _recorded_checkpoint(folder: Path, recorded: str | None) -> Path | None:
    """The checkpoint a ``preempted.json`` names, or the file of that name in the point's own ``checkpoints/`` when
    the point's folder has moved since (a curve run in one folder and published, resumable, into ``sweeps/``).
    None if neither exists."""
    if not recorded:
        return None
    path = Path(recorded)
    if path.exists():
        return path
    moved = folder / "checkpoints" / path.name
    return moved if moved.exists() else None


def _killed_attempt(folder: Path) -> dict | None:
    """The record of an attempt killed outright (no ``preempted.json``, no ``results.json``) that left a periodic
    ``checkpoints/last.ckpt``: its step and the seconds its saved steps cost (``graf.callbacks.AttemptClock``).
    None if there is no such checkpoint, or it cannot be read (the point then starts again, its ``checkpoints/``
    moved aside to ``checkpoints.unreadable``: graf-train refuses a new run beside an interrupted run's checkpoint)."""
    ckpt = folder / "checkpoints" / "last.ckpt"
    if (folder / "results.json").exists() or not ckpt.exists():
        return None
    # lazy: torch adds seconds to the command's start-up, and only a killed attempt needs it
    from graf.models.base import read_checkpoint

    try:
        state = read_checkpoint(ckpt, lightning=False)
        step = int(state["global_step"])
    except Exception as e:  # noqa: BLE001  (a truncated or foreign file: start the point again, say so)
        aside, k = folder / "checkpoints.unreadable", 1
        while aside.exists():
            aside, k = folder / f"checkpoints.unreadable_{k}", k + 1
        (folder / "checkpoints").rename(aside)
        log.warning("%s: its checkpoint cannot be read (%s); moved to %s, starting the point again", ckpt, e, aside)
        return None
    attempt = state.get("graf_attempt") or {}
    fit_s = attempt.get("fit_s") if attempt.get("global_step") == step else None
    return {
        "killed": True,
        "global_step": step,
        "start_step": attempt.get("start_step"),
        "checkpoint": str(ckpt),
        "fit_s": fit_s,
    }


def attempt_devices(preempted: list[dict], last: str | None) -> str | None:
    """The devices a point's attempts trained on, in order and each once (``NVIDIA H200 + cpu``); an attempt whose
    record names none (written before pre-emption records held one) is left out."""
    names = [short_device(p.get("device")) for p in preempted] + [short_device(last)]
    seen = [n for n in names if n]
    return " + ".join(dict.fromkeys(seen)) or None


@task_wrapper
def curves(cfg: DictConfig) -> dict:
    """Run every selected regime's KNN line and methods' curves as far as ``until``, then write and print the
    tables (resumable: a finished point is skipped)."""
    check_settings(cfg)
    out = Path(cfg.out) if cfg.get("out") else output_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if cfg.get("threads"):
        env["OMP_NUM_THREADS"] = str(cfg.threads)
    common = [f"data_root={cfg.data_root}"] + ([f"torch_threads={cfg.threads}"] if cfg.get("threads") else [])
    failed_file = out / "failed.json"
    failed = json.loads(failed_file.read_text()) if failed_file.exists() else []
    for rname, regime in subset(cfg.regimes, cfg.get("only_regimes"), "only_regimes").items():
        base = [*regime.overrides, *common, *QUIET, *(cfg.get("extra_overrides") or [])]
        knn_dir = out / rname / "knn"
        if not (knn_dir / "results.json").exists():
            cmd = [*TRAIN, *base, "model=knn", f"hydra.run.dir={knn_dir}"]
            ok, tail = run_command(cmd, knn_dir, env, float(cfg.run_timeout_s))
            if not ok:
                failed.append({"regime": rname, "method": "knn", "step": 0, "log": tail})
        for mname in regime_methods(cfg, rname):
            failed = _run_curve(cfg, out, env, rname, mname, base, failed)
    atomic_write_json(failed_file, failed)
    rows, knn = collect(out, cfg)
    write_outputs(out, rows, knn, failed)
    print((out / "curves.md").read_text())
    return {"rows": rows, "knn": knn, "failed": failed}


def regime_methods(cfg: DictConfig, rname: str) -> list[str]:
    """The methods (of ``only_methods``) whose curve regime ``rname`` has: all but those whose ``only_in`` lists
    other regimes (NeRF2, one scene's field, has no zero-shot curve) and, where the regime lists its ``methods``,
    those it does not list; each skipped one named in the log."""
    keep = []
    listed = cfg.regimes[rname].get("methods")
    for mname, method in subset(cfg.methods, cfg.get("only_methods"), "only_methods").items():
        if listed is not None and mname not in listed:
            log.info("%s: no %s curve (the regime's methods: %s)", rname, mname, ", ".join(listed))
            continue
        only_in = method.get("only_in")
        if only_in is not None and rname not in only_in:
            log.info("%s: no %s curve (its only_in: %s)", rname, mname, ", ".join(only_in))
            continue
        keep.append(mname)
    return keep


def _run_curve(cfg: DictConfig, out: Path, env: dict, rname: str, mname: str, base: list, failed: list) -> list:
    """Train method ``mname``'s points of regime ``rname`` not done before, each resuming the previous one, the
    outputs rewritten after each; the failures, updated (a failed point ends the curve)."""
    regime, method = cfg.regimes[rname], cfg.methods[mname]
    extra = list((method.get("regimes") or {}).get(rname) or [])
    own = own_runs(regime, rname)
    prev = None
    for step in points(cfg, regime):
        folder = out / rname / mname / f"step_{step}"
        if (folder / "results.json").exists():
            prev = None if own else folder
            continue
        cmd = [
            *TRAIN,
            *base,
            *method.overrides,
            *extra,
            f"{method.schedule}={step if own else int(regime.max_steps)}",
            f"trainer.max_steps={step}",
            f"callbacks.model_checkpoint.every_n_train_steps={min(step, int(cfg.checkpoint_every))}",
            f"hydra.run.dir={folder}",
        ]
        link_checkpoints(folder, cfg.get("checkpoint_root"))
        start = resume_from(folder, prev)
        if start is not None:
            cmd.append(f"ckpt_path={start}")
        log.info(
            "%s / %s: training to step %d%s", rname, mname, step, f" from {start.parent.parent.name}" if start else ""
        )
        ok, tail = _run_point(cmd, folder, env, cfg, out, failed)
        if not ok:
            failed.append({"regime": rname, "method": mname, "step": step, "log": tail})
            atomic_write_json(out / "failed.json", failed)
            if own:  # the other points are runs of their own: they go on
                log.error("%s / %s step %d failed:\n%s", rname, mname, step, tail)
                continue
            log.error("%s / %s step %d failed (the curve stops here):\n%s", rname, mname, step, tail)
            break
        if not cfg.get("keep_checkpoints"):  # the curve resumes from its newest last.ckpt only
            _remove_checkpoints(folder, prev)
            if own:  # nothing resumes from a run of its own once it is done
                drop_checkpoints(folder)
        # a point that now succeeded is no longer a failure (an earlier attempt's record goes)
        failed = [f for f in failed if (f["regime"], f["method"], f["step"]) != (rname, mname, step)]
        atomic_write_json(out / "failed.json", failed)
        prev = None if own else folder
        rows, knn = collect(out, cfg)
        write_outputs(out, rows, knn, failed)
    return failed


def _run_point(cmd: list[str], folder: Path, env: dict, cfg: DictConfig, out: Path, failed: list) -> tuple[bool, str]:
    """Run one point; a pre-emption (of this command, or of the run alone) writes the outputs and stops the command
    with :class:`graf.errors.Preempted`."""
    try:
        ok, tail = run_command(cmd, folder, env, float(cfg.run_timeout_s))
        if not ok and (folder / "preempted.json").exists():  # the run alone got the SIGTERM
            raise Preempted(f"SIGTERM: {folder} was pre-empted; run the same command again to resume\n{tail}")
    except Preempted:
        rows, knn = collect(out, cfg)
        write_outputs(out, rows, knn, failed)
        raise
    return ok, tail


def _remove_checkpoints(folder: Path, prev: Path | None) -> None:
    """Keep only the newest point's ``last.ckpt``: its ModelCheckpoint copies and the previous point's go."""
    for f in (folder / "checkpoints").glob("*.ckpt"):
        if f.name != "last.ckpt":  # ModelCheckpoint's copy of the same weights
            f.unlink()
    if prev is not None:
        drop_checkpoints(prev)


def link_checkpoints(folder: Path, root) -> None:
    """With ``checkpoint_root`` set, a point's ``checkpoints/`` is a link to a folder under it (the point's absolute
    path mirrored there), so the checkpoints a curve resumes from stay outside the repository; a point that already
    has a folder of its own keeps it."""
    link = folder / "checkpoints"
    if root is None or link.exists() or link.is_symlink():
        return
    target = Path(str(root)).expanduser() / folder.resolve().relative_to(folder.resolve().anchor) / "checkpoints"
    target.mkdir(parents=True, exist_ok=True)
    folder.mkdir(parents=True, exist_ok=True)
    link.symlink_to(target, target_is_directory=True)


def drop_checkpoints(folder: Path) -> None:
    """Remove a point's checkpoints: the folder, or the linked one and its link (``checkpoint_root``)."""
    link = folder / "checkpoints"
    if link.is_symlink():
        shutil.rmtree(link.resolve(), ignore_errors=True)
        link.unlink()
    else:
        shutil.rmtree(link, ignore_errors=True)
