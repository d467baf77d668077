"""graf-show-scenes: a picture of a few spectra from each simulated scene's dataset at one band.

    graf-show-scenes data_root=DIR band=2.4ghz [scenes=[conference_v1,outdoor]] [count=4] [out=DIR]

Writes ``scenes.png`` and ``results.json`` (per scene: file, spectra, mean traced paths per position,
file size) into its output folder (and ``out``).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import hydra
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from graf.app.config import output_dir, task_wrapper  # noqa: E402
from graf.data.spectrum_set import DataFormatError  # noqa: E402
from graf.io import atomic_write_json  # noqa: E402
from graf.plotting import SPECTRUM_CMAP, SPECTRUM_LABEL, save_figure  # noqa: E402
from graf.sim.dataset import read_dataset  # noqa: E402


@task_wrapper
def show(cfg: DictConfig) -> dict:
    band = hydra.utils.instantiate(cfg.band)
    rows, summary = [], {}
    for name in cfg.scenes:
        path = dataset_file(Path(cfg.data_root), name, band.name, cfg.get("num_tx"))
        d = read_dataset(path)
        pick = np.linspace(0, len(d.ids) - 1, int(cfg.count)).round().astype(int)
        rows.append((name, d, pick))
        summary[name] = {
            "file": str(path),
            "spectra": int(len(d.ids)),
            "mb": round(path.stat().st_size / 1e6, 1),
            "mean_paths_per_position": round(float(np.mean(d.meta["num_paths"])), 1),
        }
    out = output_dir(cfg)
    save_figure(scenes_figure(rows, int(cfg.count), band.name), out / "scenes.png", dpi=70)
    result = {"band": band.name, "scenes": summary, "figure": "scenes.png"}
    atomic_write_json(out / "results.json", result)
    if cfg.get("out"):
        Path(cfg.out).mkdir(parents=True, exist_ok=True)
        shutil.copy(out / "scenes.png", Path(cfg.out) / f"scenes_{band.name}.png")
        atomic_write_json(Path(cfg.out) / f"scenes_{band.name}.json", result)
    for name, s in summary.items():
        print(
            f"{name:<15} {s['spectra']:>6} spectra  {s['mean_paths_per_position']:>6.1f} paths/position  "
            f"{s['mb']:>7.1f} MB"
        )
    return result


def dataset_file(data_root: Path, name: str, band: str, num_tx: int | None) -> Path:
    """The dataset file of scene ``name`` at ``band`` (the limited one of ``num_tx`` positions when given); a
    missing one is a :class:`DataFormatError` saying how to make it."""
    suffix = "" if num_tx is None else f"-n{int(num_tx)}"
    path = data_root / "sim" / name / f"{band}{suffix}.h5"
    if not path.is_file():
        limited = sorted(p.name for p in path.parent.glob(f"{band}-n*.h5"))
        raise DataFormatError(
            path,
            f"no dataset; make it with graf-simulate scene={name} band={band}"
            + (f" (limited ones there: {limited}; show them with num_tx=N)" if limited else ""),
        )
    return path


def scenes_figure(rows, count: int, band: str):
    """A row of ``count`` spectra per scene (``rows``: name, dataset, the picked rows)."""
    fig, axes = plt.subplots(
        len(rows), count, figsize=(3.2 * count, 1.25 * len(rows) + 0.6), squeeze=False, constrained_layout=True
    )
    for r, (name, d, pick) in enumerate(rows):
        for c, i in enumerate(pick):
            ax = axes[r, c]
            ax.imshow(
                d.spectra[i].numpy(),
                origin="lower",
                extent=(0.5, 360.5, 0.5, 90.5),
                aspect="auto",
                vmin=0,
                vmax=1,
                cmap=SPECTRUM_CMAP,
            )
            p = d.positions[i]
            ax.set_title(f"{name} id {int(d.ids[i])} ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) m", fontsize=7)
            # degrees on the outer panels only: azimuth along the bottom row, elevation up the first column
            ax.set_xticks([90, 180, 270, 360] if r == len(rows) - 1 else [])
            ax.set_yticks([1, 45, 90] if c == 0 else [])
            ax.tick_params(labelsize=6)
    if rows:
        fig.colorbar(axes[0, 0].images[0], ax=axes.ravel().tolist(), shrink=0.9, label=SPECTRUM_LABEL)
    fig.suptitle(f"Simulated spectra at {band} (azimuth 1-360 deg across, elevation 1-90 deg up)", fontsize=9)
    return fig
