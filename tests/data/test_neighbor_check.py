"""The set-up neighbor check inspects what a stage will select: graf-eval never selects training targets, so a
scene whose training split is too small for the run's sparse neighbors is evaluated, and training on it is refused
before it starts."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from graf.bands import Band
from graf.data.datamodule import SpectrumDataModule
from graf.data.neighbors import NeighborSelector, NoNeighborsError
from graf.data.nerf2_format import write_nerf2_folder
from graf.data.scenes import NeRF2Scene
from graf.run.evaluate import evaluate
from graf.run.train import train
from tests.conftest import smooth_spectra

# Training split: ids 1 and 2, 1 cm apart, and id 3, a metre away; the validation seed (0) carves id 3 out for
# validation, so the fit part is ids 1 and 2, each the other's only candidate and closer than a quarter wavelength
# (3.1 cm at 2.4 GHz): sparse neighbors leave a training target none.  Validation and test targets keep theirs.
POSITIONS = np.array([[0.0, 1.0, 0.0], [0.01, 1.0, 0.0], [1.0, 1.0, 0.0], [0.5, 1.2, 0.3], [0.6, 0.8, 0.5]])


def sparse_scene(root: Path) -> Path:
    ids = np.arange(1, len(POSITIONS) + 1)
    gateway = (np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 0.0, 1.0]))
    return write_nerf2_folder(
        root / "sparse_scene", smooth_spectra(POSITIONS), POSITIONS, ids, *gateway, train_ids=ids[:3], test_ids=ids[3:]
    )


def test_setup_checks_the_targets_the_stage_selects(tmp_path):
    dm = SpectrumDataModule(
        NeRF2Scene("sparse_scene", str(sparse_scene(tmp_path))),
        Band("2.4ghz", 2.412e9),
        NeighborSelector(L=10, L_train=(3, 10), radius=10.0, exclude_within=0.25),
        batch_size=2,
    )
    dm.setup("test")  # an evaluation: validation and test targets, each with a neighbor
    assert dm.ids[dm.fit_rows].tolist() == [1, 2] and dm.checked_splits == {"val", "test"}
    with pytest.raises(NoNeighborsError, match="scene sparse_scene: target 0 .*no candidate neighbor"):
        dm.setup("fit")  # training selects the fit targets: none has a neighbor


def test_graf_eval_tests_a_scene_too_sparse_to_train_on(compose_cfg, tmp_path):
    folder = sparse_scene(tmp_path)
    common = (
        "scene=nerf2",
        f"scene.nerf2.path={folder}",
        "band=2.4ghz",
        "neighbors=sparse",
        "model=knn",
        "plot_count=0",
    )
    cfg = compose_cfg("eval", common)
    evaluate(cfg)
    results = json.loads((Path(cfg.paths.output_dir) / "results.json").read_text())
    assert results["n_test"] == 2 and math.isfinite(results["metrics"]["test/psnr"])
    with pytest.raises(NoNeighborsError, match="no candidate neighbor"):
        train(compose_cfg("train", common))
