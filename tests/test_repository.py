"""The repository stops growing by binaries (no checkpoint enters git beyond the 13 published before the rule:
.gitignore's ``*.ckpt``; a record names the command that rebuilds its checkpoint instead), and its records tree
holds no code."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PUBLISHED_BEFORE_THE_RULE = {
    f"sweeps/learning_curves/{curve}/{point}/checkpoints/last.ckpt"
    for curve, points in {
        "cross_family": ["knn_dl/step_3000", "pooled/step_3000", "ray/step_3000", "ray_knn/step_3000",
                         "ray_weights/step_3000"],
        "cross_family_val_30k": ["pooled/step_30000", "ray/step_30000"],
        "rfid_sparse": [f"{m}/step_10000" for m in ("knn_dl", "nerf2", "pooled", "ray", "ray_knn", "ray_weights")],
    }.items()
    for point in points
}  # fmt: skip


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_no_new_checkpoint_is_under_version_control():
    tracked = subprocess.run(
        ["git", "ls-files", "--cached", "*.ckpt", "*.pt", "*.pth"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    assert set(tracked) - PUBLISHED_BEFORE_THE_RULE == set()
    probe = "sweeps/learning_curves/any_regime/ray_weights/step_300/checkpoints/last.ckpt"
    ignored = subprocess.run(["git", "check-ignore", "-q", "--no-index", probe], cwd=ROOT)
    assert ignored.returncode == 0, f"{probe} is not ignored by .gitignore"
    link = "sweeps/learning_curves/any_regime/ray_weights/step_300/checkpoints"  # a link under checkpoint_root
    assert subprocess.run(["git", "check-ignore", "-q", "--no-index", link], cwd=ROOT).returncode == 0


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_the_records_tree_holds_no_code():
    """Records are data: a script that made one lives in ``scripts/`` (``scripts/records/`` for one-off runs), and the
    record's README names it."""
    tracked = subprocess.run(
        ["git", "ls-files", "--cached", "sweeps/*.py", "sweeps/*.sh"], cwd=ROOT, capture_output=True, text=True
    ).stdout.split()
    assert tracked == []


def test_figures_are_palette_pngs_that_look_the_same_at_a_fraction_of_the_size(tmp_path):
    """Every regeneration of a record's figure stays in git's history, so figures are saved once, by
    ``graf.plotting.save_figure``, as 256-colour palettes: a spectrum heatmap keeps its look (no pixel moves by more
    than a few levels of 255) at under half the bytes of matplotlib's RGBA."""
    import matplotlib.pyplot as plt
    import numpy as np
    from PIL import Image

    from graf.plotting import SPECTRUM_CMAP, save_figure

    def heatmap():
        fig, ax = plt.subplots(figsize=(6, 3))
        yy, xx = np.mgrid[0:90, 0:360]
        ax.imshow(np.sin(xx / 40.0) * np.cos(yy / 15.0), cmap=SPECTRUM_CMAP, aspect="auto")
        ax.set_title("id 7: predicted (21.3 dB)")
        return fig

    rgba = tmp_path / "rgba.png"
    fig = heatmap()
    fig.savefig(rgba, dpi=100)
    plt.close(fig)
    saved = save_figure(heatmap(), tmp_path / "record" / "spectra.png", dpi=100)
    assert sorted(p.name for p in saved.parent.iterdir()) == ["spectra.png"]  # written atomically, no leftovers
    with Image.open(saved) as im:
        assert im.mode == "P"
        palette = np.asarray(im.convert("RGB"), dtype=int)
    with Image.open(rgba) as im:
        full = np.asarray(im.convert("RGB"), dtype=int)
    assert palette.shape == full.shape
    assert np.percentile(np.abs(palette - full), 99) <= 8
    assert saved.stat().st_size < 0.5 * rgba.stat().st_size
