"""graf-interp: the interpolation theorem (supplement A.1) measured on a scene's field.

    graf-interp                                            # rfid_s23 (measured: the dataset part only)
    graf-interp 'scene=[conference_v1,office_v1]' band=2.4ghz sim_num_tx=150

For each scene of ``scene=``:

- **dataset part** (every scene): each position of the scene's dataset interpolated from its L nearest others
  (``interp.L``), barycentric and IDW weights; the error (RMSE of the spectrum, 8-bit as stored) against the
  largest neighbor distance dP, and its log-log slope with a 95% interval
  (:func:`graf.analysis.powerlaw.fit_power_law`).
- **fine scales** (simulated scenes): ``interp.anchors`` positions of the dataset, each interpolated from eight
  neighbors traced at distance ``scales_wavelengths`` x wavelength around it (float spectra, no quantisation);
  the median error per scale, its local slopes, and the scale up to which the quadratic law holds (every local
  slope from the finest scale on >= ``interp.threshold_slope``).
- **curvature** (simulated scenes): K by central second differences (step ``fd_step_wavelengths`` x wavelength)
  at the anchors, against error / dP**2 at the finest scale (Spearman's rho and a power-law fit), and a map of K
  over the floor plan at one height (``kmap_spacing_m``, ``kmap_height``), with the objects' footprints.

Writes ``results.json`` and ``interp_<scene>.png`` into the output folder and prints one line per scene.
"""

from __future__ import annotations

import json
import logging
import time
import zlib
from pathlib import Path

import matplotlib.pyplot as plt  # on the Agg backend: graf.plotting (below) sets it
import numpy as np
from omegaconf import DictConfig, OmegaConf
from scipy import stats

from graf.analysis.interpolation import (
    cluster_errors,
    curvature_map,
    interpolation_errors,
    local_slopes,
    quadratic_up_to,
)
from graf.analysis.powerlaw import fit_power_law
from graf.app.config import output_dir, scene_configs, task_wrapper
from graf.errors import ConfigError
from graf.io import atomic_write_json
from graf.plotting import save_figure
from graf.run.build import build_datamodule

log = logging.getLogger("graf")


def _fit(x, y) -> dict | None:
    try:
        f = fit_power_law(x, y)
    except ValueError as exc:
        log.warning("power-law fit skipped: %s", exc)
        return None
    return {"slope": f.slope, "ci": list(f.ci), "level": f.level, "n": f.n, "r2": f.r2, "intercept": f.intercept}


def dataset_part(positions, spectra, Ls, weightings) -> dict:
    out = {}
    for w in weightings:
        dp, err, per_l = [], [], {}
        for L in Ls:
            r = interpolation_errors(positions, spectra, int(L), w)
            dp.append(r["dp_max"])
            err.append(r["rmse"])
            per_l[int(L)] = {"median_dp_m": float(np.median(r["dp_max"])), "median_rmse": float(np.median(r["rmse"]))}
        dp, err = np.concatenate(dp), np.concatenate(err)
        out[w] = {"fit": _fit(dp, err), "per_L": per_l, "dp_max": dp.tolist(), "rmse": err.tolist()}
    return out


def fine_part(trace, anchors, scales_m, threshold: float, seed: int) -> dict:
    r = cluster_errors(trace, anchors, scales_m, seed=seed)
    out = {"scales_m": [float(s) for s in scales_m]}
    for w in ("barycentric", "idw"):
        err = r[f"rmse_{w}"]
        mids, slopes = local_slopes(r["scale"], err)
        upto = quadratic_up_to(r["scale"], err, threshold)
        small = r["scale"] <= (upto if upto is not None else 0)
        out[w] = {
            "median_rmse": [float(np.median(err[r["scale"] == s])) for s in scales_m],
            "local_slopes": {"at_m": mids.tolist(), "slope": slopes.tolist()},
            "quadratic_up_to_m": upto,
            "fit_quadratic_regime": _fit(r["dp_max"][small], err[small]) if small.sum() >= 3 else None,
            "rmse": err.tolist(),
        }
    out["anchor"], out["scale"] = r["anchor"].tolist(), r["scale"].tolist()
    return out


def _scene_trace(scene_obj, band):
    tracer, bart = scene_obj.tracer(band), scene_obj.bartlett(band)

    def trace(positions: np.ndarray) -> np.ndarray:
        _, s, _ = scene_obj.spectra(tracer, bart, positions)
        return s.reshape(len(positions), -1).numpy()

    return trace


def _plot(path, name, data, fine, kpart, kmap, objects, wavelength) -> None:
    n = 1 + (fine is not None) + (kmap is not None)
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 4.2), squeeze=False, constrained_layout=True)
    ax = axes[0, 0]
    for w, color in (("barycentric", "C0"), ("idw", "C1")):
        d = data[w]
        ax.loglog(d["dp_max"], np.maximum(d["rmse"], 1e-6), ".", ms=2, alpha=0.3, color=color, label=f"{w} (dataset)")
        if fine is not None:
            ax.loglog(fine["scales_m"], fine[w]["median_rmse"], "o-", color=color, label=f"{w} (fine, median)")
    ax.axvline(wavelength, color="gray", lw=0.8, ls=":")
    ax.set_xlabel("largest neighbor distance dP (m); dotted: one wavelength")
    ax.set_ylabel("RMSE of the interpolated spectrum")
    ax.set_title(f"{name}: error against dP", fontsize=9)
    ax.legend(fontsize=7)
    if kmap is not None:
        ax = axes[0, 1]
        xs, ys, K = np.array(kmap["x"]), np.array(kmap["y"]), np.array(kmap["K"])
        im = ax.pcolormesh(xs, ys, np.log10(np.maximum(K, 1e-12)), shading="nearest", cmap="viridis")
        for o in objects:
            (cx, cy), (sx, sy) = o["center"][:2], o["size"][:2]
            ax.add_patch(plt.Rectangle((cx - sx / 2, cy - sy / 2), sx, sy, fill=False, ec="w", lw=0.8))
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)"), ax.set_ylabel("y (m)")
        ax.set_title(f"log10 K at z = {kmap['z']:.2f} m (white: objects)", fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8, label="log10 K (1/m^2)")
    if fine is not None and kpart is not None:
        ax = axes[0, -1]
        ax.loglog(kpart["K"], kpart["ratio"], "o", ms=3)
        ax.set_xlabel("K at the anchor (1/m^2)")
        ax.set_ylabel(f"RMSE / dP^2 at dP = {kpart['scale_m']:.3g} m")
        rho = kpart.get("spearman_rho")
        ax.set_title(f"error / dP^2 against K (Spearman rho {rho:.2f})" if rho is not None else "", fontsize=9)
    save_figure(fig, path, dpi=90)


def near_far(kmap: dict, scene_obj, margin: float) -> dict | None:
    """K over the floor-plan map split by clearance: grid points within ``margin`` of a wall (the room's side
    walls; floor and ceiling are left out, the map being at one height) or of an object's box (its yaw
    included), against the open space beyond.  Median K of each, their ratio, and the counts; grid points
    inside an object are left out (nothing is traced there).  None without a map or a geometry."""
    geo = getattr(scene_obj, "geometry", None)
    if not kmap or geo is None:
        return None
    xs, ys, z = np.asarray(kmap["x"]), np.asarray(kmap["y"]), float(kmap["z"])
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], -1)
    K = np.asarray(kmap["K"], dtype=float).ravel()
    inside = geo.inside_objects(pts, 0.0)
    near = geo.inside_objects(pts, margin)
    room = getattr(scene_obj, "room", None)
    if room:
        sx, sy = float(room["size"][0]), float(room["size"][1])
        near |= np.minimum.reduce([pts[:, 0], sx - pts[:, 0], pts[:, 1], sy - pts[:, 1]]) <= margin
    keep = ~inside & np.isfinite(K) & (K > 0)
    out = {"margin_m": float(margin), "inside_objects": int(inside.sum())}
    for name, sel in (("near", keep & near), ("open", keep & ~near)):
        out[name] = {"n": int(sel.sum()), "median_K": float(np.median(K[sel])) if sel.any() else None}
    a, b = out["near"]["median_K"], out["open"]["median_K"]
    out["near_over_open"] = a / b if a and b else None
    return out


def footprints(scene_obj) -> list[dict]:
    """The scene's objects for the K map's outlines; a layout variant removes an object by setting it to null."""
    return [dict(o) for o in (getattr(scene_obj, "objects", None) or {}).values() if o]


def _finished_scenes(path: Path, config: dict) -> dict:
    """The scenes an earlier invocation into the same folder finished with the same analysis settings."""
    if not path.is_file():
        return {}
    try:
        prev = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}

    def settings(c: dict) -> dict:  # a setting added since, left at its default (null), changes nothing
        return {k: v for k, v in ((c or {}).get("interp") or {}).items() if v is not None}

    before = prev.get("config") or {}
    same = settings(before) == settings(config) and before.get("seed") == config.get("seed")
    return dict(prev.get("scenes") or {}) if same else {}


def _summary_line(name: str, rec: dict, lam: float) -> str:
    b = rec["dataset"].get("barycentric", {}).get("fit") or {}
    line = f"{name:<15} dataset slope (barycentric) {b.get('slope', float('nan')):.2f}"
    fine, kpart = rec.get("fine"), rec.get("curvature")
    if fine is not None:
        up = fine["barycentric"]["quadratic_up_to_m"]
        line += f"; quadratic up to {'-' if up is None else f'{up:.3g} m ({up / lam:.2g} wavelengths)'}"
        line += f"; rho(K, error/dP^2) {kpart['spearman_rho']:.2f}"
    nf = rec.get("kmap_near_far") or {}
    if nf.get("near_over_open"):
        line += f"; K near walls/objects / open {nf['near_over_open']:.2f}"
    return line


def _kept(prev: dict | None, band, n_positions: int, scene_obj, ic: DictConfig) -> dict | None:
    """A scene's record finished by an earlier invocation with the same settings, band and positions (the command
    is resumable per scene), brought up to date; None when there is none."""
    if prev is None or prev.get("band_hz") != float(band.frequency_hz) or prev.get("n_positions") != n_positions:
        return None
    if "kmap_near_far" not in prev and prev.get("kmap"):  # added after the record was made: no tracing
        prev["kmap_near_far"] = near_far(prev["kmap"], scene_obj, float(ic.kmap_spacing_m))
    return prev


def _curvature(trace, anchors, fine: dict, scales: list[float], h: float, lam: float, ic: DictConfig) -> dict:
    """K by finite differences at the anchors against error / dP^2 at one cluster scale (the finest unless
    interp.ratio_scale_wavelengths names another: at the finest, both it and K by finite differences can be ruled
    by the tracer's noise floor)."""
    K = curvature_map(trace, anchors, h)
    rs = ic.get("ratio_scale_wavelengths")
    at = scales[0] if rs is None else min(scales, key=lambda x: abs(x - float(rs) * lam))
    first = np.isclose(np.array(fine["scale"]), at)
    ratio = np.array(fine["barycentric"]["rmse"])[first] / at**2
    rho, p = stats.spearmanr(K, ratio)
    return {"K": K.tolist(), "ratio": ratio.tolist(), "scale_m": at, "fd_step_m": h,
            "spearman_rho": float(rho), "spearman_p": float(p), "fit_ratio_vs_K": _fit(K, ratio)}  # fmt: skip


def _kmap(trace, scene_obj, h: float, ic: DictConfig) -> dict:
    """K over the transmitters' floor plan at one height (``kmap_height``, default: mid-range)."""
    lo, hi = np.asarray(scene_obj.transmitters["min"], float), np.asarray(scene_obj.transmitters["max"], float)
    z = float(ic.kmap_height) if ic.get("kmap_height") is not None else float((lo[2] + hi[2]) / 2)
    step = float(ic.kmap_spacing_m)
    xs, ys = np.arange(lo[0], hi[0] + 1e-9, step), np.arange(lo[1], hi[1] + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], -1)
    return {"x": xs.tolist(), "y": ys.tolist(), "z": z, "K": curvature_map(trace, pts, h).reshape(gx.shape).tolist()}


def _scene_record(cfg: DictConfig, d, band, scene_obj, out: Path) -> dict:
    """One scene's parts (dataset; fine scales and curvature when simulated) and its figure."""
    t0 = time.perf_counter()
    ic, lam = cfg.interp, float(band.wavelength)
    # each scene's anchors from its own seeded stream: the same whichever scenes run with it, or resume
    rng = np.random.default_rng([int(cfg.get("seed") or 0), zlib.crc32(d.name.encode())])
    spectra = d.spectra.reshape(len(d.positions), -1).numpy()
    rec = {"band_hz": float(band.frequency_hz), "wavelength_m": lam, "n_positions": int(len(d.positions))}
    rec["dataset"] = dataset_part(d.positions, spectra, list(ic.L), list(ic.weightings))
    fine = kpart = kmap = None
    simulated = hasattr(scene_obj, "tracer") and int(ic.anchors) > 0
    if simulated:
        trace = _scene_trace(scene_obj, band)
        pick = rng.choice(len(d.positions), size=min(int(ic.anchors), len(d.positions)), replace=False)
        anchors = np.asarray(d.positions)[np.sort(pick)]
        scales = sorted(float(s) * lam for s in ic.scales_wavelengths)
        fine = fine_part(trace, anchors, scales, float(ic.threshold_slope), int(cfg.get("seed") or 0))
        h = float(ic.fd_step_wavelengths) * lam
        kpart = _curvature(trace, anchors, fine, scales, h, lam, ic)
        kmap = _kmap(trace, scene_obj, h, ic)
        rec.update(fine=fine, curvature=kpart, kmap=kmap)
        rec["kmap_near_far"] = near_far(kmap, scene_obj, float(ic.kmap_spacing_m))
    objects = footprints(scene_obj) if simulated else []
    fig = out / f"interp_{d.name}.png"
    _plot(fig, d.name, rec["dataset"], fine, kpart, kmap, objects, lam)
    rec["figure"], rec["seconds"] = fig.name, round(time.perf_counter() - t0, 3)
    return rec


@task_wrapper
def run(cfg: DictConfig) -> dict:
    """graf-interp: each scene's record (resumable per scene), written after each; printed one line per scene."""
    started = time.perf_counter()
    configs = scene_configs(cfg.get("scene"))
    if not configs:
        raise ConfigError("graf-interp: scene= selects no scene")
    bands, scenes, _, dm = build_datamodule(cfg)
    dm.setup("fit")
    out = output_dir(cfg)
    results = {"analysis": "interpolation", "scenes": {}, "config": OmegaConf.to_container(cfg, resolve=True)}
    done = _finished_scenes(out / "results.json", results["config"])
    lines = []
    for d, band, scene_obj in zip(dm.sets, bands, scenes):
        kept = _kept(done.get(d.name), band, len(d.positions), scene_obj, cfg.interp)
        if kept is not None:
            log.info("%s: kept from the earlier run (%s)", d.name, out / "results.json")
        rec = kept if kept is not None else _scene_record(cfg, d, band, scene_obj, out)
        results["scenes"][d.name] = rec
        lines.append(_summary_line(d.name, rec, float(band.wavelength)))
        if kept is None:
            atomic_write_json(out / "results.json", {**results, "complete": False})  # each finished scene is kept
    results["seconds"] = round(time.perf_counter() - started, 3)
    results["complete"] = True
    atomic_write_json(out / "results.json", results)
    print("\n".join(lines))
    print(f"results: {out / 'results.json'}")
    return results
