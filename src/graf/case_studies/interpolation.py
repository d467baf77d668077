"""graf-interp: the interpolation theorem (supplement A.1) measured on a scene's field.

    graf-interp                                            # rfid_s23 (measured: the dataset part only)
    graf-interp 'scene=[conference_v1,office_v1]' band=2.4ghz sim_num_tx=150

For each scene of ``scene=``:

- **dataset part** (every scene): each position of the scene's dataset interpolated from its L nearest others
  (``interp.L``), barycentric and IDW weights; the error (RMSE of the spectrum, 8-bit as stored) against the
  largest neighbor distance dP, and its log-log slope with a 95% interval
  (:func:`fit_power_law`).
- **fine scales** (simulated scenes): ``interp.anchors`` positions of the dataset, each interpolated from eight
  neighbors traced at distance ``scales_wavelengths`` x wavelength around it (float spectra, no quantisation);
  the median error per scale, its local slopes, and the scale up to which the quadratic law holds (every local
  slope from the finest scale on >= ``interp.threshold_slope``).
- **curvature** (simulated scenes): K by central second differences (step ``fd_step_wavelengths`` x wavelength)
  at the anchors, against error / dP**2 at the finest scale (Spearman's rho and a power-law fit), and a map of K
  over the floor plan at one height (``kmap_spacing_m``, ``kmap_height``), with the objects' footprints.

Writes ``results.json`` and ``interp_<scene>.png`` into the output folder and prints one line per scene.

**The measures.** The interpolation theorem measured (supplement A.1): the error of a convex combination of neighbors'
spectra against the largest neighbor distance dP, and the local curvature constant K that bounds it
(``error <= K dP**2`` where the field is smooth).

- :func:`interpolation_errors`: every target of a set interpolated from its L nearest other positions with
  barycentric or IDW weights; per target the largest neighbor distance and the mean squared error.
- :func:`curvature`: K at a position from a field ``trace(positions) -> spectra`` (the simulator), by central
  second differences along the three axes: the root mean square over pixels of the largest second directional
  derivative (per metre squared).
- :func:`fit_power_law`: a power law fitted on log-log axes, with its confidence interval (the theorem's check:
  the error grows as ``K * dP**2``, so its log-log slope against the largest neighbor distance should be 2 where
  the law holds).

This module is longer than the house's 400 lines (``tests/test_import_graph.py``, ``LONG_MODULES``): the measures
and the study that runs them are one case study, one file per case study, and cutting the theorem's measures from
its study would make a reader look in two places again.
"""

from __future__ import annotations

import json
import logging
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt  # on the Agg backend: graf.plotting (below) sets it
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from scipy import stats
from scipy.spatial.transform import Rotation

from graf.app.config import output_dir, task_wrapper
from graf.app.spec import RunSpec
from graf.data.neighbors import select_neighbors
from graf.errors import ConfigError
from graf.io import atomic_write_json
from graf.models.knn.weights import barycentric_weights, idw_weights
from graf.plotting import save_figure
from graf.run.build import build_datamodule

WEIGHTINGS = ("barycentric", "idw")


def interpolation_errors(
    positions, spectra, L: int, weighting: str = "barycentric", targets=None, chunk: int = 256
) -> dict[str, np.ndarray]:
    """Interpolate each target's spectrum from its ``L`` nearest other positions of the set.

    ``positions`` ``[N, 3]`` (m), ``spectra`` ``[N, 90, 360]`` (or ``[N, P]``); ``targets``: the rows to
    interpolate (default: all).  Returns ``{"target", "dp_max", "dp_mean", "mse", "rmse"}``, one entry per
    target: the largest and mean neighbor distance (m) and the (root) mean squared error of the interpolated
    spectrum.  The theorem bounds the error itself, so its slope against ``dp_max`` is read on ``rmse``."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting={weighting!r}: one of {', '.join(WEIGHTINGS)}")
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float64)
    spec = torch.as_tensor(np.asarray(spectra), dtype=torch.float64).reshape(pos.shape[0], -1)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be [N, 3], got {list(pos.shape)}")
    n = pos.shape[0]
    if n < 2:
        raise ValueError("interpolation needs at least two positions")
    rows = torch.arange(n) if targets is None else torch.as_tensor(np.asarray(targets), dtype=torch.long)
    ids = torch.arange(n)
    out = {k: [] for k in ("target", "dp_max", "dp_mean", "mse")}
    for start in range(0, len(rows), chunk):
        t = rows[start : start + chunk]
        nb = select_neighbors(pos[t], pos, min(L, n - 1), target_ids=ids[t], cand_ids=ids)
        nbr = pos[nb.index]
        w = (barycentric_weights if weighting == "barycentric" else idw_weights)(pos[t], nbr, nb.mask).double()
        pred = torch.einsum("tl,tlp->tp", w, spec[nb.index])
        d = torch.where(nb.mask, nb.distance.double(), torch.zeros_like(nb.distance.double()))
        out["target"].append(t.numpy())
        out["dp_max"].append(d.amax(dim=1).numpy())
        out["dp_mean"].append((d.sum(dim=1) / nb.mask.sum(dim=1)).numpy())
        out["mse"].append(((pred - spec[t]) ** 2).mean(dim=1).numpy())
    res = {k: np.concatenate(v) for k, v in out.items()}
    res["rmse"] = np.sqrt(res["mse"])
    return res


def curvature(trace: Callable[[np.ndarray], np.ndarray], position, h: float) -> float:
    """K at ``position`` (m): RMS over pixels of the largest |second derivative| along x, y, z, from central
    differences with step ``h`` (m) of ``trace`` (``[M, 3]`` positions -> ``[M, ...]`` spectra)."""
    if not h > 0:
        raise ValueError(f"the finite-difference step must be > 0 m, got {h}")
    p = np.asarray(position, dtype=np.float64).reshape(3)
    pts = [p] + [p + s * h * e for e in np.eye(3) for s in (1.0, -1.0)]
    s = np.asarray(trace(np.stack(pts)), dtype=np.float64).reshape(7, -1)
    second = np.stack([(s[1 + 2 * i] - 2.0 * s[0] + s[2 + 2 * i]) / h**2 for i in range(3)])  # [3, P]
    return float(np.sqrt(np.mean(np.abs(second).max(axis=0) ** 2)))


# the 8 corners of a cube: a target at their centre lies inside their convex hull, so barycentric weights exist
_CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) / np.sqrt(3.0)


def cluster_errors(trace: Callable[[np.ndarray], np.ndarray], anchors, scales, seed: int = 0) -> dict[str, np.ndarray]:
    """Interpolation error at fine scales, from a field ``trace`` (the simulator): around every anchor and for
    every scale ``d`` (m), eight neighbors towards the corners of a randomly rotated cube (each direction jittered,
    one per octant) at distances drawn in [d/2, d] (the largest set to d, so ``dp_max == d``); the anchor is
    interpolated from them with barycentric and IDW weights.  Returns ``{"anchor", "scale", "dp_max",
    "rmse_barycentric", "rmse_idw"}`` (one entry per anchor and scale), all traced in one call per scale."""
    anchors = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("anchor", "scale", "dp_max", "rmse_barycentric", "rmse_idw")}
    for d in np.asarray(scales, dtype=np.float64):
        if not d > 0:
            raise ValueError(f"scales must be > 0 m, got {d}")
        rot = Rotation.random(len(anchors), random_state=rng).as_matrix()  # [A, 3, 3]
        # the corners jittered (one per octant still, so the anchor stays inside the hull), so that the directions
        # do not sum to zero: on an exactly symmetric set IDW would reproduce a linear field by accident
        dirs = _CUBE[None] + 0.2 * rng.standard_normal((len(anchors), 8, 3))
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        radius = rng.uniform(0.5, 1.0, size=(len(anchors), 8)) * d
        radius[np.arange(len(anchors)), rng.integers(0, 8, len(anchors))] = d
        offsets = np.einsum("aij,akj->aki", rot, dirs) * radius[..., None]  # [A, 8, 3]
        nbr = anchors[:, None, :] + offsets
        pts = np.concatenate([anchors[:, None, :], nbr], axis=1).reshape(-1, 3)
        s = np.asarray(trace(pts), dtype=np.float64).reshape(len(anchors), 9, -1)
        tgt, nb_s = torch.from_numpy(anchors), torch.from_numpy(nbr)
        mask = torch.ones(len(anchors), 8, dtype=torch.bool)
        for name, fn in (("barycentric", barycentric_weights), ("idw", idw_weights)):
            w = fn(tgt, nb_s, mask).double().numpy()
            pred = np.einsum("al,alp->ap", w, s[:, 1:])
            out[f"rmse_{name}"].append(np.sqrt(np.mean((pred - s[:, 0]) ** 2, axis=1)))
        out["anchor"].append(np.arange(len(anchors)))
        out["scale"].append(np.full(len(anchors), d))
        out["dp_max"].append(np.linalg.norm(offsets, axis=-1).max(axis=1))
    return {k: np.concatenate(v) for k, v in out.items()}


def local_slopes(scale, error) -> tuple[np.ndarray, np.ndarray]:
    """The log-log slope of the median error between consecutive scales: ``(midpoints, slopes)``; a slope near 2
    is the theorem's quadratic regime, near 0 a field decorrelated at that distance."""
    scale, error = np.asarray(scale, dtype=np.float64), np.asarray(error, dtype=np.float64)
    s = np.unique(scale)
    med = np.array([np.median(error[scale == v]) for v in s])
    if len(s) < 2:
        return np.array([]), np.array([])
    slopes = np.diff(np.log10(np.maximum(med, 1e-300))) / np.diff(np.log10(s))
    return np.sqrt(s[1:] * s[:-1]), slopes


def quadratic_up_to(scale, error, threshold: float = 1.5) -> float | None:
    """The largest scale (m) up to which every local slope from the finest scale on stays >= ``threshold``: where
    the quadratic law holds (None when it does not hold even between the two finest scales)."""
    mids, slopes = local_slopes(scale, error)
    s = np.unique(np.asarray(scale, dtype=np.float64))
    last = None
    for i, sl in enumerate(slopes):
        if sl < threshold:
            break
        last = float(s[i + 1])
    return last


def curvature_map(trace: Callable[[np.ndarray], np.ndarray], points, h: float, chunk: int = 128) -> np.ndarray:
    """:func:`curvature` at every point ``[M, 3]``, the stencils of ``chunk`` points traced per call (memory
    bounded: an outdoor floor grid of 8,000 points in one call, 56,000 spectra, once took all 24 GB)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    stencil = np.concatenate([np.zeros((1, 3))] + [s * h * e[None] for e in np.eye(3) for s in (1.0, -1.0)])
    out = []
    for i in range(0, len(pts), max(1, int(chunk))):
        part = pts[i : i + max(1, int(chunk))]
        batch = (part[:, None, :] + stencil[None]).reshape(-1, 3)
        spectra = np.asarray(trace(batch), dtype=np.float64).reshape(len(part), 7, -1)
        out += [curvature(lambda _p, s=s: s, p, h) for p, s in zip(part, spectra)]
    return np.array(out, dtype=np.float64).reshape(len(pts))


@dataclass(frozen=True)
class PowerLaw:
    """``y = 10**intercept * x**slope`` fitted by least squares on log10 axes over ``n`` points; ``ci``: the
    slope's two-sided confidence interval at ``level`` (Student t, n - 2 degrees of freedom)."""

    slope: float
    intercept: float
    ci: tuple[float, float]
    level: float
    n: int
    r2: float

    def __call__(self, x):
        return 10.0**self.intercept * np.asarray(x, dtype=np.float64) ** self.slope


def fit_power_law(x, y, level: float = 0.95) -> PowerLaw:
    """Fit ``log10 y = slope * log10 x + intercept``.  Points where x or y is not finite and positive are left
    out (a zero error has no logarithm); at least three must remain."""
    x, y = np.asarray(x, dtype=np.float64).ravel(), np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in length: {x.size} and {y.size}")
    keep = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    lx, ly = np.log10(x[keep]), np.log10(y[keep])
    n = int(lx.size)
    if n < 3:
        raise ValueError(f"a power-law fit needs at least 3 positive points, got {n}")
    if np.ptp(lx) == 0:
        raise ValueError("all x are equal: the slope is undefined")
    res = stats.linregress(lx, ly)
    t = stats.t.ppf(0.5 + level / 2.0, n - 2)
    half = float(t * res.stderr)
    return PowerLaw(
        slope=float(res.slope),
        intercept=float(res.intercept),
        ci=(float(res.slope) - half, float(res.slope) + half),
        level=float(level),
        n=n,
        r2=float(res.rvalue**2),
    )


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
    spec = RunSpec.of(cfg)
    if not spec.scenes:
        raise ConfigError("graf-interp: scene= selects no scene")
    bands, scenes, _, dm = build_datamodule(spec)
    dm.setup("fit")
    out = output_dir(cfg)
    results = {"analysis": "interpolation", "scenes": {}, "config": OmegaConf.to_container(cfg, resolve=True)}
    done = _finished_scenes(out / "results.json", results["config"])
    lines = []
    for d, band, scene_obj in zip(dm.sets, bands, scenes):
        kept = _kept(done.get(d.name), band, len(d.positions), scene_obj, cfg.interp)
        if kept is not None:  # its figure is drawn again from its record (the figure code may be newer)
            log.info("%s: kept from the earlier run (%s); its figure redrawn", d.name, out / "results.json")
            objects = footprints(scene_obj) if kept.get("kmap") else []
            parts = (kept.get("fine"), kept.get("curvature"), kept.get("kmap"))
            _plot(out / kept["figure"], d.name, kept["dataset"], *parts, objects, float(band.wavelength))
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
