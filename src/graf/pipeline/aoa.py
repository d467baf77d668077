"""graf-aoa: the AoA case study (seed): the direct path's angle of arrival estimated from each method's predicted
spectra, against the geometric truth and against the AoA of the true spectra.

    graf-eval model=knn save_predictions=true hydra.run.dir=runs/knn      # any run with save_predictions=true
    graf-aoa 'runs=[runs/knn,runs/graf]'

For every run folder (``results.json`` and ``predictions.npz`` of graf-train or graf-eval on one scene): the test
positions and the gateway's pose come from the run's own scene (its config in ``results.json``); per test
spectrum, :func:`graf.analysis.aoa.peak_direction` of the predicted and of the true spectrum, and
:func:`graf.analysis.aoa.arrival_direction` of the transmitter.  Reports per method the median and 90th
percentile of three great-circle errors (degrees): predicted vs geometry, true spectrum vs geometry (what the
measurement itself allows), predicted vs true spectrum; and the method's test PSNR and neighbour reliance beside.
Writes ``results.json``, ``aoa.md`` and ``aoa_cdf.png`` into the output folder.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from scipy.spatial.transform import Rotation

from graf.analysis.aoa import angular_error, arrival_direction, peak_direction
from graf.errors import ConfigError
from graf.io import atomic_write_json, atomic_write_text
from graf.pipeline.build import build_datamodule
from graf.pipeline.config import output_dir, task_wrapper
from graf.plotting import save_figure

ERRORS = ("pred_vs_geometry", "true_vs_geometry", "pred_vs_true")


def _summary(err: np.ndarray) -> dict:
    return {"median": float(np.median(err)), "p90": float(np.percentile(err, 90)), "mean": float(np.mean(err))}


def run_errors(folder: Path, data_root: str | None) -> dict:
    """AoA errors of one run folder (see the module doc)."""
    res_path, pred_path = folder / "results.json", folder / "predictions.npz"
    for p in (res_path, pred_path):
        if not p.is_file():
            raise ConfigError(f"{p}: missing (run graf-train or graf-eval with save_predictions=true into {folder})")
    res = json.loads(res_path.read_text())
    cfg = OmegaConf.create(res["config"])
    if data_root is not None:
        cfg.data_root = data_root
    _, _, _, dm = build_datamodule(cfg, "eval_scene" if cfg.get("eval_scene") else "scene")
    dm.setup("fit")
    if len(dm.sets) != 1:
        raise ConfigError(f"{folder}: graf-aoa reads runs tested on one scene, this one has {len(dm.sets)}")
    d = dm.sets[0]
    arr = np.load(pred_path)
    row = {int(i): k for k, i in enumerate(np.asarray(d.ids))}
    missing = [int(i) for i in arr["ids"] if int(i) not in row]
    if missing:
        raise ConfigError(f"{pred_path}: ids {missing[:5]} are not in scene {d.name}'s dataset")
    pos = np.asarray(d.positions)[[row[int(i)] for i in arr["ids"]]]
    rot = Rotation.from_quat(np.asarray(d.gateway_orientation, dtype=np.float64)).as_matrix()
    g_el, g_az = arrival_direction(pos, np.asarray(d.gateway_position, dtype=np.float64), rot)
    pe = np.array([peak_direction(s) for s in arr["pred"]])
    te = np.array([peak_direction(s) for s in arr["target"]])
    errs = {
        "pred_vs_geometry": angular_error(pe[:, 0], pe[:, 1], g_el, g_az),
        "true_vs_geometry": angular_error(te[:, 0], te[:, 1], g_el, g_az),
        "pred_vs_true": angular_error(pe[:, 0], pe[:, 1], te[:, 0], te[:, 1]),
    }
    m = res.get("metrics") or {}
    return {
        "folder": str(folder),
        "method": res.get("method"),
        "scene": d.name,
        "n": int(len(arr["ids"])),
        "test_psnr": m.get("test/psnr"),
        "test_reliance_db": m.get("test/reliance_db"),
        **{k: _summary(v) for k, v in errs.items()},
        "per_spectrum": {"ids": [int(i) for i in arr["ids"]], **{k: v.tolist() for k, v in errs.items()}},
    }


def markdown(rows: list[dict]) -> str:
    head = (
        "| method | scene | n | AoA error vs geometry (median / p90, deg) | true spectra vs geometry | "
        "vs the true spectra's AoA | test PSNR | reliance dB |"
    )
    lines = [head, "|" + "---|" * 8]
    for r in rows:
        f = lambda k, r=r: f"{r[k]['median']:.1f} / {r[k]['p90']:.1f}"  # noqa: E731
        psnr = "-" if r["test_psnr"] is None else f"{r['test_psnr']:.2f}"
        rel = "-" if r["test_reliance_db"] is None else f"{r['test_reliance_db']:.2f}"
        lines.append(
            f"| {r['method']} | {r['scene']} | {r['n']} | {f('pred_vs_geometry')} | {f('true_vs_geometry')} | "
            f"{f('pred_vs_true')} | {psnr} | {rel} |"
        )
    return "\n".join(lines)


def _plot(path: Path, rows: list[dict]) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    done_truth = set()
    for r in rows:
        e = np.sort(r["per_spectrum"]["pred_vs_geometry"])
        ax.plot(e, np.arange(1, len(e) + 1) / len(e), label=f"{r['method']} ({r['scene']})")
        if r["scene"] not in done_truth:
            t = np.sort(r["per_spectrum"]["true_vs_geometry"])
            ax.plot(t, np.arange(1, len(t) + 1) / len(t), "k--", lw=1, label=f"true spectra ({r['scene']})")
            done_truth.add(r["scene"])
    ax.set_xscale("log")
    ax.set_xlabel("AoA error against the geometry (degrees)")
    ax.set_ylabel("fraction of test positions")
    ax.legend(fontsize=7)
    save_figure(fig, path, dpi=100)


@task_wrapper
def run(cfg: DictConfig) -> dict:
    started = time.perf_counter()
    if not cfg.get("runs"):
        raise ConfigError("graf-aoa: give runs=[<run folder>, ...] (runs with save_predictions=true)")
    rows = [run_errors(Path(str(f)), cfg.get("data_root")) for f in cfg.runs]
    out = output_dir(cfg)
    table = markdown(rows)
    _plot(out / "aoa_cdf.png", rows)
    atomic_write_text(out / "aoa.md", table + "\n")
    atomic_write_json(out / "results.json", {"analysis": "aoa", "runs": rows, "figure": "aoa_cdf.png",
                                             "seconds": round(time.perf_counter() - started, 3)})  # fmt: skip
    print(table)
    print(f"results: {out / 'results.json'}")
    return {"runs": rows}
