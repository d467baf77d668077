"""graf-pareto: GRaF's speed/accuracy trade, measured (the knobs of ``conf/pareto.yaml``).

    graf-pareto [out=DIR] [threads=N]

For each scene: one ``graf-train`` run per training point (the base, and each knob changed alone: voxel size
in wavelengths, rays per step, encoder width and downsampling, training path, precision, training steps,
neighbor-feature mode, another method), then ``graf-eval``
of the base checkpoint per evaluation point (L at test).  Each run is a separate process writing its own
folder ``<out>/<scene>/<point>/`` (results.json, run.log); a point whose results.json exists is skipped, so a
killed sweep continues where it stopped, and a failed run is recorded in ``failed.json`` while the others go
on.  A simulated scene whose dataset is missing under ``data_root`` is simulated first.

After every run the tables are rewritten (atomically): ``pareto.md``, ``pareto.csv``, ``results.json`` (a
list ``rows``: scene, point, knob, value, train_s, train_s_per_step, infer_s_per_spectrum, val_psnr,
test_psnr, knn_test_psnr, front_infer, front_train) and ``pareto.png`` (test PSNR against inference time and
against training time, one row of panels per scene).  Times: ``train_s`` is the wall time of the fit
(``timing.fit_s`` of graf-train; an evaluation point inherits its base's), ``infer_s_per_spectrum`` the test
loop per spectrum (prediction and the four metrics).  **The Pareto fronts use validation PSNR**: a point is
on the front when no other point of the scene is at least as fast with a higher validation PSNR; the test
PSNR is reported beside it, never used to choose.  Points of ``reference_knobs`` (another method at the base
budget) are tabled and drawn but left out of the fronts, which rank GRaF's own settings.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import time
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from graf.app.config import check_int, output_dir, task_wrapper
from graf.app.launch import command
from graf.errors import ConfigError, as_override
from graf.io import atomic_write_json, atomic_write_text
from graf.studies.runner import run_command

log = logging.getLogger("graf")

COLUMNS = (
    "scene",
    "point",
    "knob",
    "value",
    "train_s",
    "train_s_per_step",
    "infer_s_per_spectrum",
    "val_psnr",
    "test_psnr",
    "knn_test_psnr",
    "front_infer",
    "front_train",
)


def _dataset_missing(cfg: DictConfig, sim: list[str]) -> bool:
    scene = next(o.split("=", 1)[1] for o in sim if o.startswith("scene="))
    band = next(o.split("=", 1)[1] for o in sim if o.startswith("band="))
    return not (Path(cfg.data_root) / "sim" / scene / f"{band}.h5").exists()


def pareto_front(rows: list[dict], cost: str, score: str = "val_psnr") -> set[int]:
    """Indices of the rows on the front of (low ``cost``, high ``score``): no other row is at most as costly
    with a strictly higher score, or strictly cheaper with the same score."""
    front = set()
    for i, r in enumerate(rows):
        if r.get(cost) is None or r.get(score) is None:
            continue
        dominated = any(
            o is not r
            and o.get(cost) is not None
            and o.get(score) is not None
            and o[cost] <= r[cost]
            and o[score] >= r[score]
            and (o[cost] < r[cost] or o[score] > r[score])
            for o in rows
        )
        if not dominated:
            front.add(i)
    return front


ONLY = {"only_scenes": ("scene", ("scenes",)), "only_points": ("point", ("points", "eval_points"))}


def _selected(cfg: DictConfig, group: str, only: str) -> dict:
    """The entries of ``group`` whose keys the list ``only`` (``only_scenes``, ``only_points``) names (null: all);
    a name of no scene (point) stops with one line listing the known ones."""
    items = dict(cfg.get(group) or {})
    keep = cfg.get(only)
    if keep is None:
        return items
    what, groups = ONLY[only]
    if not isinstance(keep, (list, ListConfig)):  # only_points=base was read letter by letter
        raise ConfigError(f"{only}={as_override(keep)}: must be a list of {what}s, such as [{keep}]")
    known = sorted({k for g in groups for k in cfg.get(g) or {}})
    if unknown := set(keep) - set(known):
        raise ConfigError(f"{only}: {sorted(unknown)} is no {what} of the config ({what}s: {known})")
    return {k: v for k, v in items.items() if k in set(keep)}


def reference_knobs(cfg: DictConfig) -> set[str]:
    """The knobs whose points are references outside the fronts; each must be the knob of some point."""
    listed = cfg.get("reference_knobs") or []
    if not isinstance(listed, (list, ListConfig)):  # reference_knobs=method was read letter by letter
        raise ConfigError(f"reference_knobs={as_override(listed)}: must be a list of knobs, such as [{listed}]")
    reference = set(listed)
    points = {**(cfg.get("points") or {}), **(cfg.get("eval_points") or {})}
    knobs = {p.knob for p in points.values()}
    if unknown := reference - knobs:
        raise ConfigError(f"reference_knobs: {sorted(unknown)} is the knob of no point (knobs: {sorted(knobs)})")
    return reference


def collect(out: Path, cfg: DictConfig) -> list[dict]:
    """One row per finished run, fronts marked per scene."""
    rows = []
    for scene in _selected(cfg, "scenes", "only_scenes"):
        base_train = None
        scene_rows = []
        for kind, points in (
            ("train", _selected(cfg, "points", "only_points")),
            ("eval", _selected(cfg, "eval_points", "only_points")),
        ):
            for name, p in points.items():
                f = out / scene / name / "results.json"
                if not f.exists():
                    continue
                r = json.loads(f.read_text())
                t = r.get("timing") or {}
                m = r["metrics"]
                row = {
                    "scene": scene,
                    "point": name,
                    "knob": p.knob,
                    "value": str(p.value),
                    "train_s": t.get("fit_s"),
                    "train_s_per_step": t.get("fit_s_per_step"),
                    "infer_s_per_spectrum": t.get("test_s_per_spectrum"),
                    "val_psnr": m.get("val/psnr"),
                    "test_psnr": m.get("test/psnr"),
                    "knn_test_psnr": ((r.get("baselines") or {}).get("knn") or {}).get("metrics", {}).get("test/psnr"),
                }
                if kind == "train" and name == "base":
                    base_train = (row["train_s"], row["train_s_per_step"])
                if kind == "eval" and base_train is not None:  # no training of its own: the base's
                    row["train_s"], row["train_s_per_step"] = base_train
                scene_rows.append(row)
        # the fronts are GRaF's own settings: a point of a reference knob (another method) is tabled and drawn, not
        # ranked, so that it does not hide GRaF's trade behind it
        reference = reference_knobs(cfg)
        ranked = [i for i, row in enumerate(scene_rows) if row["knob"] not in reference]
        on = {
            cost: {ranked[j] for j in pareto_front([scene_rows[i] for i in ranked], cost)}
            for cost in ("infer_s_per_spectrum", "train_s")
        }
        for i, row in enumerate(scene_rows):
            row["front_infer"], row["front_train"] = i in on["infer_s_per_spectrum"], i in on["train_s"]
        rows += scene_rows
    return rows


def _fmt(v, spec=".2f"):
    return "n/a" if v is None else (format(v, spec) if isinstance(v, float) else str(v))


def write_tables(out: Path, rows: list[dict], failed: list[dict], meta: dict) -> None:
    lines = [
        "| scene | point | knob | value | train s | train s/step | infer s/spectrum | val PSNR | test PSNR | "
        "KNN test PSNR | front (infer) | front (train) |",
        "|" + "---|" * 12,
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['point']} | {r['knob']} | {r['value']} | {_fmt(r['train_s'], '.1f')} | "
            f"{_fmt(r['train_s_per_step'], '.3f')} | {_fmt(r['infer_s_per_spectrum'], '.3f')} | "
            f"{_fmt(r['val_psnr'])} | {_fmt(r['test_psnr'])} | {_fmt(r['knn_test_psnr'])} | "
            f"{'yes' if r['front_infer'] else ''} | {'yes' if r['front_train'] else ''} |"
        )
    lines.append("")
    reference = (meta.get("config") or {}).get("reference_knobs") or []
    outside = f" (points of knob {', '.join(reference)}: references, outside the fronts)" if reference else ""
    lines.append(
        f"Fronts on validation PSNR{outside}; test PSNR reported, never used to choose. Times: "
        f"{meta['device']}, {meta['threads']} threads."
    )
    atomic_write_text(out / "pareto.md", "\n".join(lines) + "\n")
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS)
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(out / "pareto.csv", buf.getvalue())
    atomic_write_json(out / "results.json", {**meta, "rows": rows, "failed": failed})
    if rows:
        plot(out / "pareto.png", rows)


PANELS = (
    ("infer_s_per_spectrum", "inference s / spectrum", "front_infer"),
    ("train_s", "training s (whole fit)", "front_train"),
)  # (cost column, axis label, front column) of each panel


def plot(path: Path, rows: list[dict]) -> None:
    """Test PSNR against inference and training time, one row of panels per scene; written atomically."""
    # lazy: pyplot adds about 0.4 s to the command's start-up, and only the figure needs it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from graf.plotting import save_figure

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    knobs = list(dict.fromkeys(r["knob"] for r in rows))
    # one marker and one colour per knob, the same in every panel
    markers = {k: (m, plt.get_cmap("tab10")(i % 10)) for i, (k, m) in enumerate(zip(knobs, "o^sDvP*Xh<>"))}
    fig, axes = plt.subplots(len(scenes), 2, figsize=(11, 4.2 * len(scenes)), squeeze=False)
    for i, scene in enumerate(scenes):
        sr = [r for r in rows if r["scene"] == scene]
        for j, (cost, label, front) in enumerate(PANELS):
            ax = axes[i][j]
            _draw_points(ax, sr, cost, front, markers)
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.set_xlabel(label)
            ax.set_ylabel("test PSNR (dB)")
            ax.set_title(f"{scene}")
            handles, labels = ax.get_legend_handles_labels()
            uniq = dict(zip(labels, handles))
            ax.legend(uniq.values(), uniq.keys(), fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def _draw_points(ax, sr: list[dict], cost: str, front: str, markers: dict) -> None:
    """One scene's points, its front (chosen on validation PSNR) and the KNN line, against one cost."""
    for r in sr:
        if r[cost] is None or r["test_psnr"] is None:
            continue
        ax.scatter(
            r[cost],
            r["test_psnr"],
            marker=markers[r["knob"]][0],
            color=markers[r["knob"]][1],
            s=60 if r[front] else 30,
            edgecolors="k" if r[front] else "none",
            label=r["knob"],
        )
    fr = sorted((r for r in sr if r[front] and r[cost] is not None), key=lambda r: r[cost])
    # labels on the front's points alone, alternating above and below the line (the rest crowd together:
    # their marker names their knob, pareto.md their value)
    for k, r in enumerate(fr):
        at = (4, 5) if k % 2 == 0 else (4, -11)
        ax.annotate(f"{r['value']}", (r[cost], r["test_psnr"]), fontsize=7, xytext=at, textcoords="offset points")
    for r in sr:  # another method is named wherever it lies (it stands apart from GRaF's knobs)
        if r["knob"] == "method" and not r[front] and r[cost] is not None and r["test_psnr"] is not None:
            xy = (r[cost], r["test_psnr"])
            ax.annotate(f"{r['value']}", xy, fontsize=7, xytext=(4, 5), textcoords="offset points")
    if fr:
        ax.plot([r[cost] for r in fr], [r["test_psnr"] for r in fr], "k--", lw=0.8, label="front (chosen on val PSNR)")
    knn = next((r["knn_test_psnr"] for r in sr if r["knn_test_psnr"] is not None), None)
    if knn is not None:
        ax.axhline(knn, color="gray", lw=1, ls=":", label="KNN")


def _device() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip() + f" ({os.cpu_count()} cores)"
    except OSError:
        pass
    return "cpu"


def _child_env(cfg: DictConfig) -> dict:
    """The environment of every run: this one, with ``threads`` and an absolute ``GRAF_DATA_ROOT``."""
    env = dict(os.environ)
    if cfg.get("threads"):
        env["OMP_NUM_THREADS"] = str(cfg.threads)
    env["GRAF_DATA_ROOT"] = str(Path(cfg.data_root).resolve())
    return env


def _simulated(cfg: DictConfig, scene: str, sc: DictConfig, out: Path, env: dict, failed: list[dict]) -> bool:
    """Whether the scene's dataset is there, simulated first if it was missing (a failure is added to ``failed``
    and written)."""
    sim = list(sc.get("simulate") or [])
    if not sim or not _dataset_missing(cfg, sim):
        return True
    log.info("%s: dataset missing under %s, simulating it first", scene, cfg.data_root)
    folder = out / scene / "_simulate"
    cmd = command("graf-simulate", *sim, f"data_root={env['GRAF_DATA_ROOT']}")
    ok, tail = run_command([*cmd, f"hydra.run.dir={folder}"], folder, env, cfg.run_timeout_s)
    if ok and not _dataset_missing(cfg, sim):
        return True
    failed.append({"scene": scene, "point": "_simulate", "log": tail})
    atomic_write_json(out / "failed.json", failed)
    return False


def _jobs(cfg: DictConfig, sc: DictConfig, ckpt: Path) -> list[tuple[str, str, list[str]]]:
    """``(point, command name, command)`` of a scene: a graf-train per training point, then a graf-eval of the
    base checkpoint ``ckpt`` per evaluation point."""
    common = list(sc.get("common") or [])
    jobs = [
        (name, "graf-train", command("graf-train", *sc.get("train", []), *common, *cfg.base, *p.overrides))
        for name, p in _selected(cfg, "points", "only_points").items()
    ]
    evaluate = [f"ckpt_path={ckpt}", *common, "logger=none", "plot_count=0"]
    jobs += [
        (name, "graf-eval", command("graf-eval", *evaluate, *p.overrides))
        for name, p in _selected(cfg, "eval_points", "only_points").items()
    ]
    return jobs


def _run_scene(
    cfg: DictConfig, scene: str, sc: DictConfig, out: Path, env: dict, failed: list[dict], meta: dict
) -> list[dict]:
    """Run the scene's points not done before (a training point killed before its results.json resumes from its
    checkpoint; tables rewritten after each); the failures, updated."""
    skip = set(sc.get("skip_points") or [])
    ckpt = out / scene / "base" / "checkpoints" / "last.ckpt"
    for name, kind, cmd in _jobs(cfg, sc, ckpt):
        folder = out / scene / name
        if name in skip:
            log.info("%s / %s: skipped (scenes.%s.skip_points)", scene, name, scene)
            continue
        if (folder / "results.json").exists():
            log.info("%s / %s: done before, skipped", scene, name)
            continue
        if kind == "graf-eval" and not ckpt.exists():
            failed.append({"scene": scene, "point": name, "log": f"no base checkpoint {ckpt}"})
            atomic_write_json(out / "failed.json", failed)
            continue
        killed = folder / "checkpoints" / "last.ckpt"
        if kind == "graf-train" and killed.is_file():  # an attempt killed before its results.json: resumed
            cmd = [*cmd, f"ckpt_path={killed}"]
        log.info("%s / %s: %s", scene, name, " ".join(cmd[3:]))
        t0 = time.perf_counter()
        ok, tail = run_command(cmd + [f"hydra.run.dir={folder}"], folder, env, cfg.run_timeout_s)
        log.info("%s / %s: %s in %.0f s", scene, name, "done" if ok else "FAILED", time.perf_counter() - t0)
        if not ok:
            failed = [f for f in failed if not (f["scene"] == scene and f["point"] == name)]
            failed.append({"scene": scene, "point": name, "command": cmd[1:], "log": tail})
            atomic_write_json(out / "failed.json", failed)
        write_tables(out, collect(out, cfg), failed, meta)
    return failed


@task_wrapper
def sweep(cfg: DictConfig) -> dict:
    """Run every selected scene's points not done before, then write and print the tables."""
    reference_knobs(cfg)  # a misspelt knob stops here, before any run; so do a misspelt scene or point
    _selected(cfg, "scenes", "only_scenes")
    _selected(cfg, "points", "only_points")
    check_int(cfg.get("threads"), "threads", none=True)
    out = Path(cfg.out) if cfg.get("out") else output_dir(cfg)
    out.mkdir(parents=True, exist_ok=True)
    env = _child_env(cfg)
    failed_path = out / "failed.json"
    failed = json.loads(failed_path.read_text()) if failed_path.exists() else []
    meta = {
        "device": _device(),
        "threads": cfg.get("threads") or "default",
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    started = time.perf_counter()
    for scene, sc in _selected(cfg, "scenes", "only_scenes").items():
        if _simulated(cfg, scene, sc, out, env, failed):
            failed = _run_scene(cfg, scene, sc, out, env, failed, meta)
    rows = collect(out, cfg)
    write_tables(out, rows, failed, meta)
    print((out / "pareto.md").read_text() if (out / "pareto.md").exists() else "no finished runs")
    log.info("graf-pareto: %d rows, %d failed, %.0f s; %s", len(rows), len(failed), time.perf_counter() - started, out)
    return {"rows": rows, "failed": failed}
