"""graf-localize: the localization case study (the paper: synthesized spectra "help initialize learning-based
localization models more effectively than random initialization").

    graf-localize 'runs=[<run folder>, ...]'          # graf-train / graf-eval runs on one scene each

Each run folder (``results.json``, and ``checkpoints/last.ckpt`` unless its method trains nothing) is one
*synthesizer*: its model, conditioned on its own neighbor pool.  Its scene, measured part (``finetune``'s
fraction) and pool are rebuilt from its config, so the runs of ``experiment=unseen_layouts`` (each fine-tuned
on 5-100% of a scene) give the learning curve against the number of measured spectra.  Runs that share a scene
and measured part form a *group*; per group:

- **measured set**: the run's measured training spectra with their positions (what a survey gives);
- **test set**: the scene's test split (true spectra in, positions out): never trained on, never used to
  choose anything; every budget below is fixed in the config before looking;
- **synthetic positions**: ``n_synth`` positions uniform in the box of the scene's training split, each at
  least ``min_gap_wavelengths`` from every test position (:func:`check_disjoint`
  refuses anything closer, and a measured set holding a test position);
- **synthesizers**: every run of the group, and IDW KNN on the same pool (``knn=true``), predict spectra
  at the synthetic positions; each one's test PSNR (its predictions at the test positions, same pool) is
  its *synthesis quality* (on the first ``quality_test_count`` test positions when set: a study job's own
  test budget, so the figure equals that job's test PSNR);
- **localizers** (:class:`SpectrumLocalizer`), per seed: ``random`` (random
  initialisation, ``train_steps`` on the measured set) and one per synthesizer (``pretrain_steps`` on its
  synthesized spectra, then the same ``train_steps`` on the measured set with a fresh Adam).

Reports per group and initialisation the median and 90th-percentile localization error on the test positions
(metres; mean over seeds, each seed's figures kept), beside the synthesizer's quality and the run's neighbor
reliance.  ``results.json`` is rewritten after every group (a killed run resumes at the next group), with each
group's wall time and the command's over all its invocations (``seconds``; results written before this kept only
the last invocation's); ``localize.md`` and ``localize.png`` (median error against the number of measured
spectra, a panel per scene).

**The localizer.** Localization from spectra (the paper's claim that synthesized spectra initialise a localization
model better than random initialisation): a small CNN from a spectrum to the transmitter's position, and the splits
that keep the test positions out of everything it trains on.

- :class:`SpectrumLocalizer`: ``[B, 90, 360]`` spectra -> ``[B, 3]`` positions in the scene box's normalised
  coordinates ([-1, 1] per axis); azimuth is padded circularly (the spectrum wraps at 360 deg).
- :func:`synthetic_positions`: positions to synthesize spectra at for pre-training, uniform in a box and at least
  ``min_gap`` from every test position, so that no synthesized copy of a test position is trained on.
- :func:`check_disjoint`: refuses a training set with a position within ``min_gap`` of a test position.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import matplotlib.pyplot as plt  # on the Agg backend: graf.plotting (below) sets it
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torch.nn import functional as F

from graf.app.config import CONF_DIR, output_dir, task_wrapper
from graf.app.spec import RunSpec
from graf.case_studies.synthesis import load_model, synthesize
from graf.errors import ConfigError
from graf.io import atomic_write_json, atomic_write_text
from graf.metrics.functional import psnr_per_sample
from graf.plotting import save_figure
from graf.run.build import build_datamodule


class SpectrumLocalizer(nn.Module):
    """A small CNN: average-pool 2x, three strided convolutions (circular in azimuth), a pooled 3 x 6 map, an MLP."""

    def __init__(self, widths: tuple[int, int, int] = (16, 32, 64), hidden: int = 128):
        super().__init__()
        c1, c2, c3 = widths
        self.convs = nn.ModuleList(
            [nn.Conv2d(1, c1, 5, stride=2), nn.Conv2d(c1, c2, 3, stride=2), nn.Conv2d(c2, c3, 3, stride=2)]
        )
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c3 * 18, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def features(self, spectra: torch.Tensor, layers: int | None = None) -> torch.Tensor:
        """The feature maps after the first ``layers`` convolutions (all by default): ``[B, C, h, w]``."""
        x = F.avg_pool2d(spectra.unsqueeze(1), 2)  # [B, 1, 45, 180]
        for conv in self.convs[:layers]:
            k = conv.kernel_size[0] // 2
            x = F.pad(x, (k, k, 0, 0), mode="circular")  # azimuth wraps
            x = F.pad(x, (0, 0, k, k), mode="replicate")  # elevation does not
            x = F.relu(conv(x))
        return x

    def forward(self, spectra: torch.Tensor) -> torch.Tensor:  # [B, 90, 360] -> [B, 3]
        return self.head(F.adaptive_avg_pool2d(self.features(spectra), (3, 6)))


def normalise(positions, box_min, box_max) -> np.ndarray:
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    return 2.0 * (np.asarray(positions, dtype=np.float64) - lo) / np.maximum(hi - lo, 1e-9) - 1.0


def denormalise(coords, box_min, box_max) -> np.ndarray:
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    return (np.asarray(coords, dtype=np.float64) + 1.0) / 2.0 * (hi - lo) + lo


def _min_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if len(b) == 0:
        return np.full(len(a), np.inf)
    return torch.cdist(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)).amin(1).numpy()


def synthetic_positions(box_min, box_max, n: int, exclude, min_gap: float, seed: int = 0) -> np.ndarray:
    """``n`` positions uniform in the box, each at least ``min_gap`` (m) from every position of ``exclude``
    (the test positions); refused when the box leaves too little room."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
    ex = np.asarray(exclude, dtype=np.float64).reshape(-1, 3)
    out: list[np.ndarray] = []
    for _ in range(100):
        cand = rng.uniform(lo, hi, size=(max(2 * n, 64), 3))
        out.append(cand[_min_distance(cand, ex) >= min_gap])
        if sum(len(o) for o in out) >= n:
            return np.concatenate(out)[:n]
    raise ConfigError(
        f"localization: only {sum(len(o) for o in out)} of {n} synthetic positions fit in the box {lo.tolist()} - "
        f"{hi.tolist()} at least {min_gap} m from the {len(ex)} test positions: lower min_gap or n"
    )


def check_disjoint(train_positions, test_positions, min_gap: float, what: str = "training set") -> None:
    """Refuse a training (or synthesized) set with a position closer than ``min_gap`` to a test position."""
    d = _min_distance(np.asarray(train_positions, dtype=np.float64).reshape(-1, 3), np.asarray(test_positions))
    bad = np.flatnonzero(d < min_gap)
    if len(bad):
        raise ConfigError(
            f"localization: the {what} holds {len(bad)} position(s) within {min_gap} m of a test position (first: "
            f"row {int(bad[0])}, {float(d[bad[0]]):.4f} m): a test position or its copy would be trained on"
        )


log = logging.getLogger("graf")

# the settings a group's figures depend on: a resumed invocation must give the same ones
SETTINGS = ("knn", "n_synth", "synth_seed", "min_gap_wavelengths", "quality_test_count", "seeds", "localizer")


def read_run(folder: Path, data_root: str | None) -> dict:
    """One run folder: its config, method, checkpoint (None for a method with nothing to train), the
    datamodule of the scene it was tested on, and its neighbor reliance."""
    res_path = folder / "results.json"
    if not res_path.is_file():
        raise ConfigError(f"{res_path}: missing (give the folder of a graf-train or graf-eval run)")
    res = json.loads(res_path.read_text())
    if "config" not in res:
        raise ConfigError(f"{res_path}: holds no 'config' (not a graf-train or graf-eval run's results.json)")
    cfg = OmegaConf.create(res["config"])
    if data_root is not None:
        cfg.data_root = data_root
    if cfg.get("data") is not None:  # the localizers see the whole test split; the synthesizer's quality is
        cfg.data.test_subset = None  # measured on its first quality_test_count (a run may have tested fewer)
    spec = RunSpec.of(cfg)
    _, _, _, dm = build_datamodule(spec, "eval_scene" if spec.eval_scenes else "scene")
    dm.setup("fit")
    if len(dm.sets) != 1:
        raise ConfigError(f"{folder}: graf-localize reads runs tested on one scene, this one has {len(dm.sets)}")
    ckpt = folder / "checkpoints" / "last.ckpt"
    m = res.get("metrics") or {}
    return {
        "folder": str(folder),
        "cfg": cfg,
        "method": res.get("method") or str(cfg.model._target_).rsplit(".", 1)[-1],
        "ckpt": str(ckpt) if ckpt.is_file() else None,
        "dm": dm,
        "reliance_db": m.get("test/reliance_db"),
        "knn_reliance_db": (((res.get("baselines") or {}).get("knn") or {}).get("metrics") or {}).get(
            "test/reliance_db"
        ),
    }


def group_key(dm) -> tuple:
    """Runs with the same scene, measured part and neighbor pool share a measured set and a KNN synthesizer."""
    pool = dm.split_rows("test")[1]
    return dm.sets[0].name, tuple(dm.ids[dm.measured_rows].tolist()), tuple(dm.ids[pool].tolist())


def _psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    return float(psnr_per_sample(pred.float(), target.float()).mean())


def train_localizer(
    net: SpectrumLocalizer, spectra: torch.Tensor, coords: torch.Tensor, steps: int, lr: float, batch_size: int,
    seed: int,
) -> SpectrumLocalizer:  # fmt: skip
    """``steps`` Adam steps of mean squared error on normalised coordinates, minibatches drawn with a seeded
    generator (the same draws for every initialisation)."""
    if steps <= 0:
        return net
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    net.train()
    for _ in range(steps):
        idx = torch.randint(len(spectra), (min(batch_size, len(spectra)),), generator=g)
        loss = torch.nn.functional.mse_loss(net(spectra[idx]), coords[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    net.eval()
    return net


@torch.no_grad()
def localization_errors(net: SpectrumLocalizer, spectra: torch.Tensor, positions: np.ndarray, box) -> np.ndarray:
    """Euclidean errors (m) of the localizer's positions for ``spectra`` against ``positions``."""
    pred = denormalise(torch.cat([net(s) for s in spectra.split(64)]).numpy(), *box)
    return np.linalg.norm(pred - positions, axis=1)


def _summary(err: np.ndarray) -> dict:
    return {"median_m": float(np.median(err)), "p90_m": float(np.percentile(err, 90))}


def run_group(runs: list[dict], cfg: DictConfig) -> dict:
    """The localization learning-curve point of one group (see the module doc)."""
    dm = runs[0]["dm"]
    d = dm.sets[0]
    wavelength = float(dm.band.wavelength)
    pos = dm.positions.numpy()
    measured, test, train = (np.asarray(r) for r in (dm.measured_rows, dm.test_rows, dm.train_rows))
    test_pos, meas_pos = pos[test], pos[measured]
    min_gap = float(cfg.min_gap_wavelengths) * wavelength
    check_disjoint(meas_pos, test_pos, 1e-9, "measured set")  # a test position itself is never measured
    box = (pos[train].min(0), pos[train].max(0))  # the survey area: the training split's positions, no spectrum
    syn_pos = synthetic_positions(*box, int(cfg.n_synth), test_pos, min_gap, seed=int(cfg.synth_seed))
    check_disjoint(syn_pos, test_pos, min_gap, "synthesized set")
    synth = _synthesize_all(runs, cfg, syn_pos, test_pos)
    meas_x, test_x = dm.spectra[measured].float(), dm.spectra[test].float()
    meas_y = torch.as_tensor(normalise(meas_pos, *box), dtype=torch.float32)
    syn_y = torch.as_tensor(normalise(syn_pos, *box), dtype=torch.float32)
    inits: dict[str, dict] = {}
    for init in ["random", *synth]:
        pretrain = None if init == "random" else (synth[init]["spectra"].float(), syn_y)
        per_seed = [_localize(cfg.localizer, int(seed), pretrain, (meas_x, meas_y), test_x, test_pos, box)
                    for seed in cfg.seeds]  # fmt: skip
        inits[init] = {
            "median_m": float(np.mean([s["median_m"] for s in per_seed])),
            "p90_m": float(np.mean([s["p90_m"] for s in per_seed])),
            "per_seed": per_seed,
            **({k: v for k, v in synth[init].items() if k != "spectra"} if init in synth else {}),
        }
        log.info("%s, %d measured, %s: median %.3f m, p90 %.3f m", d.name, len(measured), init,
                 inits[init]["median_m"], inits[init]["p90_m"])  # fmt: skip
    return {
        "scene": d.name,
        "n_measured": int(len(measured)),
        "n_test": int(len(test)),
        "n_synth": int(len(syn_pos)),
        "min_gap_m": min_gap,
        "synthetic_min_distance_to_test_m": float(
            torch.cdist(torch.as_tensor(syn_pos), torch.as_tensor(test_pos)).min()
        ),
        "runs": [r["folder"] for r in runs],
        "inits": inits,
    }


def _synthesize_all(runs: list[dict], cfg: DictConfig, syn_pos: np.ndarray, test_pos: np.ndarray) -> dict:
    """``{synthesizer: its spectra at syn_pos, its synthesis quality, ...}``: each run's model, and KNN on the
    group's first run's data when ``cfg.knn`` and no run is KNN."""
    dm = runs[0]["dm"]
    d, test = dm.sets[0], np.asarray(dm.test_rows)
    # synthesis quality on the first n_q spectra of the seeded test split (all unless quality_test_count says)
    n_q = len(test) if cfg.get("quality_test_count") is None else cfg.quality_test_count
    if isinstance(n_q, bool) or not isinstance(n_q, int) or not 1 <= n_q <= len(test):
        raise ConfigError(
            f"graf-localize: quality_test_count={n_q}: give a whole number from 1 to {len(test)} "
            f"({d.name}'s test split holds {len(test)})"
        )
    synthesizers = [(r["method"], r) for r in runs]
    if cfg.knn and not any(r["method"] == "knn" for r in runs):
        knn = {**runs[0], "ckpt": None, "folder": None, "reliance_db": runs[0]["knn_reliance_db"]}
        synthesizers.append(("knn", knn))
    synth = {}
    for name, r in synthesizers:
        t0 = time.perf_counter()
        mcfg = OmegaConf.load(CONF_DIR / "model" / "knn.yaml") if r["folder"] is None else r["cfg"].model
        model = load_model(mcfg, r["ckpt"], f"run {r['folder']}")
        spectra = synthesize(model, r["dm"], syn_pos)
        quality = _psnr(synthesize(model, r["dm"], test_pos[:n_q]), dm.spectra[test[:n_q]])
        synth[name] = {"spectra": spectra, "quality_psnr": quality, "quality_n_test": n_q,
                       "reliance_db": r["reliance_db"], "folder": r["folder"],
                       "seconds": round(time.perf_counter() - t0, 2)}  # fmt: skip
        log.info("%s: %s synthesized %d spectra (test PSNR %.2f dB)", d.name, name, len(spectra), quality)
    return synth


def _localize(lc: DictConfig, seed: int, pretrain, measured, test_x, test_pos, box) -> dict:
    """One seed's localizer: pre-trained on ``pretrain`` (synthesized spectra and coordinates; None: from its
    random initialisation), trained on the ``measured`` ones; its error summary on the test spectra."""
    torch.manual_seed(seed)
    net = SpectrumLocalizer(tuple(lc.widths), int(lc.hidden))
    if pretrain is not None:
        train_localizer(net, *pretrain, int(lc.pretrain_steps), float(lc.lr), int(lc.batch_size), seed + 1000)
    train_localizer(net, *measured, int(lc.train_steps), float(lc.lr), int(lc.batch_size), seed)
    return _summary(localization_errors(net, test_x, test_pos, box))


def markdown(groups: list[dict]) -> str:
    lines = [
        "| scene | measured | init | localization error median / p90 (m) | vs random (median) | "
        "synthesis test PSNR | reliance dB |",
        "|" + "---|" * 7,
    ]
    for g in sorted(groups, key=lambda g: (g["scene"], g["n_measured"])):
        base = g["inits"]["random"]["median_m"]
        for name, r in g["inits"].items():
            q = "-" if r.get("quality_psnr") is None else f"{r['quality_psnr']:.2f}"
            rel = "-" if r.get("reliance_db") is None else f"{r['reliance_db']:.2f}"
            vs = "-" if name == "random" else f"{r['median_m'] / base:.2f}x"
            lines.append(f"| {g['scene']} | {g['n_measured']} | {name} | {r['median_m']:.3f} / {r['p90_m']:.3f} | "
                         f"{vs} | {q} | {rel} |")  # fmt: skip
    return "\n".join(lines)


def _plot(path: Path, groups: list[dict]) -> None:
    scenes = sorted({g["scene"] for g in groups})
    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 3.8), squeeze=False, constrained_layout=True)
    for ax, scene in zip(axes[0], scenes):
        gs = sorted((g for g in groups if g["scene"] == scene), key=lambda g: g["n_measured"])
        for init in sorted({i for g in gs for i in g["inits"]}, key=lambda i: (i != "random", i)):
            pts = [(g["n_measured"], g["inits"][init]["median_m"]) for g in gs if init in g["inits"]]
            ax.plot(*zip(*pts), "o-" if init != "random" else "k--", label=init)
        ax.set_xscale("log")
        ax.set_xticks([g["n_measured"] for g in gs], [str(g["n_measured"]) for g in gs])  # the surveys run
        ax.minorticks_off()
        ax.set_xlabel("measured spectra")
        ax.set_ylabel("median localization error (m)")
        ax.set_title(scene)
        ax.legend(fontsize=7)
    save_figure(fig, path, dpi=100)


@task_wrapper
def run(cfg: DictConfig) -> dict:
    started = time.perf_counter()
    if not cfg.get("runs"):
        raise ConfigError("graf-localize: give runs=[<run folder>, ...] (graf-train or graf-eval runs, one scene each)")
    torch.set_num_threads(int(cfg.threads))
    out = output_dir(cfg)
    res_path = out / "results.json"
    before = json.loads(res_path.read_text()) if res_path.is_file() else {}
    done, earlier_s = before.get("groups", []), float(before.get("seconds") or 0)  # seconds: over every invocation
    if done:  # resuming: the groups kept must have been made with these settings, or none is comparable
        made_with, now = before.get("config") or {}, OmegaConf.to_container(cfg, resolve=True)
        changed = [k for k in SETTINGS if made_with.get(k) != now.get(k)]
        if changed:
            raise ConfigError(f"{res_path}: its groups were made with other {', '.join(changed)}; "
                              "give another hydra.run.dir (or the same settings to resume)")  # fmt: skip
    groups: dict[tuple, list[dict]] = {}
    for f in cfg.runs:
        r = read_run(Path(str(f)), cfg.get("data_root"))
        groups.setdefault(group_key(r["dm"]), []).append(r)
    results = list(done)
    for runs in groups.values():
        folders = [r["folder"] for r in runs]
        if any(g["runs"] == folders for g in done):
            log.info("%s: already in %s", folders, res_path)
            continue
        t0 = time.perf_counter()
        results.append({**run_group(runs, cfg), "seconds": round(time.perf_counter() - t0, 1)})
        atomic_write_json(res_path, {"analysis": "localization", "groups": results,
                                     "config": OmegaConf.to_container(cfg, resolve=True),
                                     "seconds": round(earlier_s + time.perf_counter() - started, 1)})  # fmt: skip
    table = markdown(results)
    atomic_write_text(out / "localize.md", table + "\n")
    _plot(out / "localize.png", results)
    print(table)
    print(f"results: {res_path}")
    return {"groups": results}
