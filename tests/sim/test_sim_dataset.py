"""graf-simulate's dataset files: resumable after a kill, byte-identical for a seed, exported to and read
back from NeRF2's format, and evaluated by graf-eval."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate

import graf.sim  # noqa: F401  (configures Sionna RT's CPU backend)
from graf.app.config import CONF_DIR
from graf.bands import Band
from graf.data.nerf2_format import DataFormatError, read_nerf2_folder
from graf.run.evaluate import evaluate
from graf.sim.dataset import generate, read_dataset

pytest.importorskip("sionna.rt")

BIN = Path(sys.executable).parent
ARGS = ["scene=small_room", "band=2.4ghz", "sim.num_tx=96", "sim.chunk_size=8", "sim.progress=false"]


def _run(data_root: Path, out: Path, extra=(), **kw):
    return subprocess.Popen(
        [str(BIN / "graf-simulate"), *ARGS, f"data_root={data_root}", f"hydra.run.dir={out}", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        **kw,
    )


def _h5(root: Path) -> Path:
    return root / "sim" / "small_room" / "2.4ghz-n96.h5"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One uninterrupted run (also exports NeRF2's format)."""
    root = tmp_path_factory.mktemp("ref")
    p = _run(root, root / "out", extra=["sim.export=nerf2"])
    out, _ = p.communicate(timeout=600)
    assert p.returncode == 0, out[-3000:]
    return root


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_killed_run_resumes_without_losing_or_duplicating_spectra(reference, tmp_path):
    parts = _h5(tmp_path).with_name("2.4ghz-n96.h5.parts")
    p = _run(tmp_path, tmp_path / "out1")
    deadline = time.time() + 300
    while time.time() < deadline and len(list(parts.glob("chunk_*.npz"))) < 2 and p.poll() is None:
        time.sleep(0.02)
    p.send_signal(signal.SIGKILL)
    p.wait()
    done = sorted(parts.glob("chunk_*.npz"))
    assert 2 <= len(done) < 12 and not _h5(tmp_path).exists(), "the kill should land mid-run"
    p = _run(tmp_path, tmp_path / "out2")
    out, _ = p.communicate(timeout=600)
    assert p.returncode == 0, out[-3000:]
    result = json.loads((tmp_path / "out2" / "results.json").read_text())
    assert result["made"] == 96 - 8 * len(done)  # only the missing chunks were traced
    # same seed, same bytes: the resumed file equals the uninterrupted one
    assert _h5(tmp_path).read_bytes() == _h5(reference).read_bytes()
    assert not parts.exists()


@pytest.mark.slow  # two ray-tracing processes and three short ones: about a minute on the 2-core CI machine
def test_two_shard_processes_make_the_single_process_file(reference, tmp_path):
    """Shards 0 and 1 of 2 as two concurrent processes sharing data_root: the last to finish assembles a file
    equal, byte for byte, to one process's; a merge with a shard missing names the missing chunks."""
    procs = [
        _run(tmp_path, tmp_path / f"shard{i}", extra=[f"sim.shard.index={i}", "sim.shard.count=2"]) for i in (0, 1)
    ]
    for p in procs:
        out, _ = p.communicate(timeout=600)
        assert p.returncode == 0, out[-3000:]
    results = [json.loads((tmp_path / f"shard{i}" / "results.json").read_text()) for i in (0, 1)]
    assert [r["made"] for r in results] == [48, 48] and [r["shard_positions"] for r in results] == [[0, 48], [48, 96]]
    assert sum(r["assembled"] for r in results) == 1  # exactly one shard wrote the file
    assert _h5(tmp_path).read_bytes() == _h5(reference).read_bytes()
    assert not _h5(tmp_path).with_name("2.4ghz-n96.h5.parts").exists()

    other = tmp_path / "missing"
    p = _run(other, other / "shard1", extra=["sim.shard.index=1", "sim.shard.count=2"])
    out, _ = p.communicate(timeout=600)
    assert p.returncode == 0 and "6 chunks of other shards still missing" in out, out[-3000:]
    assert not _h5(other).exists()
    p = _run(other, other / "merge", extra=["sim.merge=true"])
    out, _ = p.communicate(timeout=600)
    assert p.returncode != 0 and "6 of 12 chunks are missing (first: chunk_00000, positions 0-7)" in out, out[-3000:]
    p = _run(other, other / "shard9", extra=["sim.shard.index=2", "sim.shard.count=2"])
    out, _ = p.communicate(timeout=600)
    assert p.returncode != 0 and "sim.shard: index 2 of count 2" in out, out[-3000:]


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_dataset_contents_and_nerf2_export_round_trip(reference):
    d = read_dataset(_h5(reference))
    assert tuple(d.spectra.shape) == (96, 90, 360) and d.n_train + d.n_test == 96
    assert float(d.spectra.max()) == 1.0 and float(d.spectra.min()) == 0.0
    assert d.meta["config"]["scene"]["name"] == "small_room" and d.meta["num_paths"].min() > 0
    folder = Path(str(_h5(reference)).replace(".h5", "_nerf2"))
    back = read_nerf2_folder(folder, frequency_hz=2.412e9)
    order = np.concatenate([d.train_idx, d.test_idx])  # the reader lists the training split first
    np.testing.assert_array_equal(back.ids, d.ids[order])
    assert bool((back.spectra == d.spectra[order]).all())  # identical values
    np.testing.assert_allclose(
        back.positions, np.concatenate([d.positions[d.train_idx], d.positions[d.test_idx]]), atol=1e-6
    )
    np.testing.assert_allclose(back.gateway_orientation, d.gateway_orientation, atol=1e-12)


@pytest.mark.slow  # moved from the default run to keep it under 5 min on the 2-core machine (issue 68)
def test_graf_eval_reads_the_simulated_scene(reference, tmp_path):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="eval",
            overrides=[
                "model=knn",
                "scene=small_room",
                "scene.small_room.num_tx=96",
                "band=2.4ghz",
                f"data_root={reference}",
                "logger=none",
                f"paths.output_dir={tmp_path}",
                "trainer.accelerator=cpu",
                "plot_count=1",
            ],
        )
    GlobalHydra.instance().clear()
    metrics, _ = evaluate(cfg)
    r = json.loads((tmp_path / "results.json").read_text())
    assert (r["scene"], r["band_hz"], r["n_test"]) == ("small_room", 2.412e9, 19)
    assert np.isfinite(metrics["test/psnr"])


def test_changed_configuration_is_refused_and_missing_dataset_is_explained(tmp_path):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="simulate", overrides=["scene=small_room", "band=2.4ghz"])
    GlobalHydra.instance().clear()
    scene, band = instantiate(cfg.scene.small_room), instantiate(cfg.band)
    parts = scene.dataset_path(tmp_path, band, 16).with_name("2.4ghz-n16.h5.parts")
    parts.mkdir(parents=True)
    (parts / "manifest.json").write_text(json.dumps({"fingerprint": "something-else"}))
    with pytest.raises(DataFormatError, match="different configuration"):
        generate(scene, band, tmp_path, num_tx=16, chunk_size=8, progress=False)
    with pytest.raises(DataFormatError, match="graf-simulate scene=small_room band=2.4ghz"):
        scene.load(tmp_path / "empty", band)


@pytest.mark.slow  # 20-72 s in a fresh-clone CI run here: the default run must stay under 15 min
def test_show_scenes_and_bench_sim_commands(reference, tmp_path):
    p = subprocess.run(
        [
            str(BIN / "graf-show-scenes"),
            f"data_root={reference}",
            "scenes=[small_room]",
            "count=2",
            "num_tx=96",
            f"hydra.run.dir={tmp_path / 'show'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    r = json.loads((tmp_path / "show" / "results.json").read_text())
    assert r["scenes"]["small_room"]["spectra"] == 96 and (tmp_path / "show" / "scenes.png").stat().st_size > 5000
    p = subprocess.run(
        [
            str(BIN / "graf-bench-sim"),
            "scene=small_room",
            "bench.num_tx=16",
            "bench.convergence_tx=8",
            f"hydra.run.dir={tmp_path / 'bench'}",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    b = json.loads((tmp_path / "bench" / "results.json").read_text())
    assert b["positions"] == 16 and b["spectra_per_second"] > 0 and "spectra/s" in p.stdout
    assert b["convergence"]["positions"] == 8 and b["convergence"]["psnr_min"] > 0


@pytest.mark.slow  # it needs the module's reference run (about 13 s), which only slow tests here share
def test_a_limited_dataset_is_read_only_when_asked_for(reference, compose_cfg):
    band = Band("2.4ghz", 2.412e9)
    scene = instantiate(compose_cfg("eval", ("scene=small_room",)).scene.small_room)
    with pytest.raises(
        DataFormatError, match=r"no dataset for scene small_room .* scene.small_room.num_tx=N \(N in \[96\]\)"
    ):
        scene.load(reference, band)  # only 2.4ghz-n96.h5 is there: never used silently
    asked = instantiate(compose_cfg("eval", ("scene=small_room", "scene.small_room.num_tx=96")).scene.small_room)
    assert len(asked.load(reference, band).ids) == 96
