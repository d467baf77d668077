"""graf-aoa: the AoA case study (the paper): the direct path's angle of arrival estimated from each method's predicted
spectra, against the geometric truth and against the AoA of the true spectra.

    graf-eval model=knn save_predictions=true hydra.run.dir=runs/knn      # any run with save_predictions=true
    graf-aoa 'runs=[runs/knn,runs/graf]'

For every run folder (``results.json`` and ``predictions.npz`` of graf-train or graf-eval on one scene): the test
positions and the gateway's pose come from the run's own scene (its config in ``results.json``); per test
spectrum, :func:`peak_direction` of the predicted and of the true spectrum, and
:func:`arrival_direction` of the transmitter.  Reports per method the median and 90th
percentile of three great-circle errors (degrees): predicted vs geometry, true spectrum vs geometry (what the
measurement itself allows), predicted vs true spectrum; and the method's test PSNR and neighbor reliance beside.
Writes ``results.json``, ``aoa.md`` and ``aoa_cdf.png`` into the output folder.

**The measure** (the seed's AoA case study): angle of arrival from a spatial spectrum, and the geometric truth to
score it against.

A spectrum is ``[90, 360]`` in the angle convention of :mod:`graf.geometry.grid`: row r is elevation r + 1 deg,
column c azimuth c + 1 deg, the direction ``(cos e cos a, cos e sin a, sin e)`` in the gateway frame.

- :func:`peak_direction`: the strongest pixel, refined to a fraction of a degree by a quadratic through it and its
  two neighbors along each axis (azimuth wraps at 360 deg; at elevation 1 or 90 deg the edge is kept).
- :func:`arrival_direction`: the direction a transmitter is seen from by the gateway (the direct path's angle of
  arrival), as (elevation, azimuth) in the same convention; a transmitter behind the array plane is mirrored into
  the front hemisphere, which is all a planar array can tell (:mod:`graf.sim.array`).
- :func:`angular_error`: the great-circle angle between two directions, in degrees.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import matplotlib.pyplot as plt  # on the Agg backend: graf.plotting (below) sets it
import numpy as np
from omegaconf import DictConfig, OmegaConf
from scipy.spatial.transform import Rotation

from graf.app.config import output_dir, task_wrapper
from graf.app.spec import RunSpec
from graf.errors import ConfigError
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION
from graf.io import atomic_write_json, atomic_write_text
from graf.plotting import save_figure
from graf.run.build import build_datamodule
from graf.run.evaluation import test_baseline


def _vertex(left: float, mid: float, right: float) -> float:
    """Offset in (-0.5, 0.5) of the vertex of the parabola through three equally spaced samples (0 if flat)."""
    den = left - 2.0 * mid + right
    if den >= 0.0 or not np.isfinite(den):  # not a strict maximum: keep the pixel
        return 0.0
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


def peak_direction(spectrum) -> tuple[float, float]:
    """``(elevation, azimuth)`` in degrees of the strongest peak of a ``[90, 360]`` spectrum, refined between
    pixels; azimuth in [0.5, 360.5) wrapped to (0, 360]."""
    s = np.asarray(spectrum, dtype=np.float64)
    if s.shape != (N_ELEVATION, N_AZIMUTH):
        raise ValueError(f"a spectrum is [{N_ELEVATION}, {N_AZIMUTH}], got {list(s.shape)}")
    if not np.isfinite(s).all():
        raise ValueError("the spectrum holds NaN or infinite values")
    r, c = np.unravel_index(int(np.argmax(s)), s.shape)
    da = _vertex(s[r, (c - 1) % N_AZIMUTH], s[r, c], s[r, (c + 1) % N_AZIMUTH])
    de = _vertex(s[r - 1, c], s[r, c], s[r + 1, c]) if 0 < r < N_ELEVATION - 1 else 0.0
    az = (c + 1 + da) % 360.0
    return float(r + 1 + de), float(az if az > 0 else az + 360.0)


def direction_to_angles(u) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions ``[..., 3]`` in the gateway frame -> (elevation, azimuth) in degrees, azimuth in (0, 360].
    A direction behind the array (z < 0) is mirrored to the front (elevation >= 0)."""
    u = np.asarray(u, dtype=np.float64)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    el = np.degrees(np.arcsin(np.clip(np.abs(u[..., 2]), 0.0, 1.0)))
    az = np.degrees(np.arctan2(u[..., 1], u[..., 0])) % 360.0
    return el, np.where(az > 0, az, az + 360.0)


def angles_to_direction(el_deg, az_deg) -> np.ndarray:
    """(elevation, azimuth) in degrees -> unit directions ``[..., 3]`` in the gateway frame."""
    e, a = np.radians(np.asarray(el_deg, dtype=np.float64)), np.radians(np.asarray(az_deg, dtype=np.float64))
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)


def arrival_direction(tx_pos, gw_pos, gw_rot) -> tuple[np.ndarray, np.ndarray]:
    """The direct path's angle of arrival of transmitters ``[..., 3]`` (m, world) at a gateway at ``gw_pos``
    with rotation matrix ``gw_rot`` (local -> world), as (elevation, azimuth) in degrees."""
    d = np.asarray(tx_pos, dtype=np.float64) - np.asarray(gw_pos, dtype=np.float64)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(n == 0):
        raise ValueError("a transmitter at the gateway's own position has no angle of arrival")
    local = (d / n) @ np.asarray(gw_rot, dtype=np.float64)  # R^T d for each row
    return direction_to_angles(local)


def angular_error(el1, az1, el2, az2) -> np.ndarray:
    """Great-circle angle in degrees between (el1, az1) and (el2, az2)."""
    u, v = angles_to_direction(el1, az1), angles_to_direction(el2, az2)
    return np.degrees(np.arccos(np.clip(np.sum(u * v, axis=-1), -1.0, 1.0)))


log = logging.getLogger("graf")

ERRORS = ("pred_vs_geometry", "true_vs_geometry", "pred_vs_true")


def _summary(err: np.ndarray) -> dict:
    return {"median": float(np.median(err)), "p90": float(np.percentile(err, 90)), "mean": float(np.mean(err))}


def _load_run(folder: Path, data_root: str | None):
    """A run folder's results, config (``data_root`` replaced when given), datamodule (set up) and its one scene."""
    res_path = folder / "results.json"
    if not res_path.is_file():
        raise ConfigError(f"{res_path}: missing (run graf-train or graf-eval with save_predictions=true into {folder})")
    res = json.loads(res_path.read_text())
    cfg = OmegaConf.create(res["config"])
    if data_root is not None:
        cfg.data_root = data_root
    spec = RunSpec.of(cfg)
    _, _, _, dm = build_datamodule(spec, "eval_scene" if spec.eval_scenes else "scene")
    dm.setup("fit")
    if len(dm.sets) != 1:
        raise ConfigError(f"{folder}: graf-aoa reads runs tested on one scene, this one has {len(dm.sets)}")
    return res, cfg, dm, dm.sets[0]


def _errors(d, pred, target, ids, where) -> dict:
    """The three AoA errors (degrees, per spectrum) of predicted and true spectra at the scene's ids."""
    row = {int(i): k for k, i in enumerate(np.asarray(d.ids))}
    missing = [int(i) for i in ids if int(i) not in row]
    if missing:
        raise ConfigError(f"{where}: ids {missing[:5]} are not in scene {d.name}'s dataset")
    pos = np.asarray(d.positions)[[row[int(i)] for i in ids]]
    rot = Rotation.from_quat(np.asarray(d.gateway_orientation, dtype=np.float64)).as_matrix()
    g_el, g_az = arrival_direction(pos, np.asarray(d.gateway_position, dtype=np.float64), rot)
    pe = np.array([peak_direction(s) for s in pred])
    te = np.array([peak_direction(s) for s in target])
    return {
        "pred_vs_geometry": angular_error(pe[:, 0], pe[:, 1], g_el, g_az),
        "true_vs_geometry": angular_error(te[:, 0], te[:, 1], g_el, g_az),
        "pred_vs_true": angular_error(pe[:, 0], pe[:, 1], te[:, 0], te[:, 1]),
    }


def _row(folder, method, d, res_splits, metrics, ids, errs) -> dict:
    return {
        "folder": str(folder),
        "method": method,
        "scene": d.name,
        "n": int(len(ids)),
        # the survey the run was trained and conditioned on (a density job's measured part), or None
        "n_measured": (res_splits or {}).get("n_measured"),
        "test_psnr": metrics.get("test/psnr"),
        "test_reliance_db": metrics.get("test/reliance_db"),
        **{k: _summary(v) for k, v in errs.items()},
        "per_spectrum": {"ids": [int(i) for i in ids], **{k: v.tolist() for k, v in errs.items()}},
    }


def run_errors(folder: Path, data_root: str | None) -> dict:
    """AoA errors of one run folder (see the module doc)."""
    pred_path = folder / "predictions.npz"
    if not pred_path.is_file():
        raise ConfigError(
            f"{pred_path}: missing (run graf-train or graf-eval with save_predictions=true into {folder})"
        )
    res, _, _, d = _load_run(folder, data_root)
    arr = np.load(pred_path)
    errs = _errors(d, arr["pred"], arr["target"], arr["ids"], pred_path)
    return _row(folder, res.get("method"), d, res.get("splits"), res.get("metrics") or {}, arr["ids"], errs)


def knn_errors(folder: Path, data_root: str | None) -> dict | None:
    """AoA errors of the KNN baseline the run was tested beside (its ``baselines.knn``), re-evaluated on the run's
    own test positions, survey and neighbors (a study job keeps only its model's predictions)."""
    res, cfg, dm, d = _load_run(folder, data_root)
    bcfg = (cfg.get("baselines") or {}).get("knn")
    if bcfg is None:
        log.warning("%s: tested without a KNN baseline (baselines.knn): no KNN row for its scene and survey", folder)
        return None
    cfg.save_predictions = False
    cfg.validate = False
    out = test_baseline(cfg, "knn", bcfg, dm)
    arr = out.arrays
    errs = _errors(d, arr["pred"], arr["target"], arr["ids"], folder)
    return _row(f"{folder} (baselines.knn)", out.method, d, res.get("splits"), out.metrics, arr["ids"], errs)


def markdown(rows: list[dict]) -> str:
    head = (
        "| method | scene | measured | n | AoA error vs geometry (median / p90, deg) | true spectra vs geometry | "
        "vs the true spectra's AoA | test PSNR | reliance dB |"
    )
    lines = [head, "|" + "---|" * 9]
    for r in rows:
        f = lambda k, r=r: f"{r[k]['median']:.1f} / {r[k]['p90']:.1f}"  # noqa: E731
        psnr = "-" if r["test_psnr"] is None else f"{r['test_psnr']:.2f}"
        rel = "-" if r["test_reliance_db"] is None else f"{r['test_reliance_db']:.2f}"
        lines.append(
            f"| {r['method']} | {r['scene']} | {r.get('n_measured') or 'all'} | {r['n']} | {f('pred_vs_geometry')} | "
            f"{f('true_vs_geometry')} | {f('pred_vs_true')} | {psnr} | {rel} |"
        )
    return "\n".join(lines)


def _plot(path: Path, rows: list[dict]) -> None:
    """The CDF of each run's AoA error (and the true spectra's): one colour per method, darker where more positions
    were measured, each run labelled with its method and measured count; the legend beside the axes, never over the
    curves (a record holds up to 20 runs).  Redrawn from a record's ``results.json`` by :func:`redraw`."""
    fig, ax = plt.subplots(figsize=(9, 4.5), constrained_layout=True)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    counts = sorted({r.get("n_measured") or 0 for r in rows})
    done_truth = set()
    for r in sorted(rows, key=lambda r: (methods.index(r["method"]), r.get("n_measured") or 0)):
        e = np.sort(r["per_spectrum"]["pred_vs_geometry"])
        shade = 0.35 + 0.65 * (counts.index(r.get("n_measured") or 0) + 1) / len(counts)
        label = f"{r['method']}, {r.get('n_measured') or 'all'} measured" + (
            f" ({r['scene']})" if len({x["scene"] for x in rows}) > 1 else ""
        )
        ax.plot(e, np.arange(1, len(e) + 1) / len(e), color=f"C{methods.index(r['method'])}", alpha=shade, label=label)
        if r["scene"] not in done_truth:
            t = np.sort(r["per_spectrum"]["true_vs_geometry"])
            ax.plot(t, np.arange(1, len(t) + 1) / len(t), "k--", lw=1, label=f"true spectra ({r['scene']})")
            done_truth.add(r["scene"])
    ax.set_xscale("log")
    ax.set_xlabel("AoA error against the geometry (degrees)")
    ax.set_ylabel("fraction of test positions")
    fig.legend(fontsize=6, loc="outside right upper", ncols=1 if len(rows) <= 12 else 2, frameon=False)
    save_figure(fig, path, dpi=100)


def redraw(folder: Path) -> Path:
    """A record's CDF figure (``aoa_cdf.png``) drawn again from its ``results.json`` alone."""
    result = json.loads((folder / "results.json").read_text())
    path = folder / result.get("figure", "aoa_cdf.png")
    _plot(path, result["runs"])
    return path


@task_wrapper
def run(cfg: DictConfig) -> dict:
    started = time.perf_counter()
    if not cfg.get("runs"):
        raise ConfigError("graf-aoa: give runs=[<run folder>, ...] (runs with save_predictions=true)")
    rows = [run_errors(Path(str(f)), cfg.get("data_root")) for f in cfg.runs]
    if cfg.get("knn"):  # KNN beside: once per scene and survey, from the first run of each
        seen = set()
        for r in rows:
            group = (r["scene"], r["n_measured"])
            if r["method"] == "knn":  # KNN's own run is that group's KNN row
                seen.add(group)
        for f, r in zip(cfg.runs, list(rows)):
            group = (r["scene"], r["n_measured"])
            if group not in seen:
                seen.add(group)
                knn = knn_errors(Path(str(f)), cfg.get("data_root"))
                if knn is not None:
                    rows.append(knn)
    rows.sort(key=lambda r: (r["scene"], r["method"] or "", r.get("n_measured") or 0))
    out = output_dir(cfg)
    table = markdown(rows)
    _plot(out / "aoa_cdf.png", rows)
    atomic_write_text(out / "aoa.md", table + "\n")
    atomic_write_json(out / "results.json", {"analysis": "aoa", "runs": rows, "figure": "aoa_cdf.png",
                                             "seconds": round(time.perf_counter() - started, 3)})  # fmt: skip
    print(table)
    print(f"results: {out / 'results.json'}")
    return {"runs": rows}
