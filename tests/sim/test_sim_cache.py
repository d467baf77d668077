"""A simulated dataset file is used only for the settings that made it, and only when it is whole.

The file records its generating configuration; ``graf-simulate`` over an existing file and every read of it
(``SimulatedScene.load``: graf-train, graf-eval, the studies) compare it with the asked settings and refuse,
in one line naming each differing setting, a file made by others.  A file whose arrays do not agree (fewer
spectra than ids, an index out of range, an empty or overlapping split) or that HDF5 cannot open (truncated)
is refused in one line naming it, never read into a traceback, never deleted.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from hydra.utils import instantiate

from graf.bands import Band
from graf.data.spectrum_set import DataFormatError
from graf.errors import ConfigError, is_user_error
from graf.run.build import build_datamodule
from graf.sim import checks
from graf.sim.dataset import read_dataset

pytest.importorskip("sionna.rt")

BIN = Path(sys.executable).parent
BAND = Band("2.4ghz", 2.412e9)
NAME = "2.4ghz-n24.h5"  # conftest's small_room_root: 24 positions of small_room at 2.4 GHz


def _copy(small_room_root: Path, tmp_path: Path) -> Path:
    """A data_root of our own holding a copy of the traced file (the session's stays untouched)."""
    dst = tmp_path / "data" / "sim" / "small_room"
    dst.mkdir(parents=True)
    shutil.copy2(small_room_root / "sim" / "small_room" / NAME, dst / NAME)
    return tmp_path / "data"


def _simulate(root: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    args = ["scene=small_room", "band=2.4ghz", "sim.num_tx=24", "sim.progress=false", f"data_root={root}"]
    return subprocess.run(
        [str(BIN / "graf-simulate"), *args, *extra, f"hydra.run.dir={out}"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


def _one_line_error(p: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2, p.stderr[-3000:] + p.stdout[-1000:]
    assert lines[-2].startswith("error: ") and "Traceback" not in p.stderr, lines
    return lines[-2]


def _scene(compose_cfg, *overrides: str):
    cfg = compose_cfg("eval", ("scene=small_room", "scene.small_room.num_tx=24", *overrides))
    return instantiate(cfg.scene.small_room)


# ---------------------------------------------------------------------------------------------- A. the cache's key


def test_graf_simulate_refuses_a_file_made_with_other_settings(small_room_root, tmp_path):
    root = _copy(small_room_root, tmp_path)
    h5 = root / "sim" / "small_room" / NAME
    before = h5.read_bytes()
    line = _one_line_error(_simulate(root, tmp_path / "moved", "scene.small_room.gateway.position=[1.0,1.0,1.5]"))
    assert "scene.small_room.gateway.position: [0.15, 1.5, 1.5] in the file, [1.0, 1.0, 1.5] asked" in line, line
    assert str(h5) in line and "sim.overwrite=true" in line and "data_root" in line, line
    assert h5.read_bytes() == before  # nothing traced over it, nothing deleted


@pytest.mark.parametrize(
    ("override", "says"),
    [
        ("sim.chunk_size=8", "sim.chunk_size: 256 in the file, 8 asked"),  # chunks batch the sources: other spectra
        ("scene.small_room.tracing.samples_per_src=20000", "scene.small_room.tracing.samples_per_src: 10000 in"),
        ("scene.small_room.objects.table=null", "scene.small_room.objects.table: {"),
        ("scene.small_room.objects.table.material=glass", "objects.table.material: 'wood' in the file, 'glass' asked"),
        ("scene.small_room.transmitters.count=500", "scene.small_room.transmitters.count: 400 in the file, 500"),
        ("scene.small_room.array.pattern=iso", "scene.small_room.array.pattern: 'cos' in the file, 'iso' asked"),
    ],
)
def test_every_setting_that_shapes_the_dataset_is_compared(small_room_root, compose_cfg, override, says):
    from graf.sim.dataset import generate

    assert generate(_scene(compose_cfg), BAND, small_room_root, num_tx=24, progress=False)["skipped"]  # the same
    scene = _scene(compose_cfg, *([override] if override.startswith("scene.") else ()))
    chunk = int(override.split("=")[1]) if override.startswith("sim.chunk_size") else 256
    with pytest.raises(DataFormatError, match="made with other settings") as err:
        generate(scene, BAND, small_room_root, num_tx=24, chunk_size=chunk, progress=False)
    assert says in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_a_dataset_of_fewer_than_two_positions_is_refused_before_tracing(compose_cfg, tmp_path):
    from graf.sim.dataset import generate

    with pytest.raises(ConfigError, match="sim.num_tx=1: a dataset needs at least 2 positions"):
        generate(_scene(compose_cfg), BAND, tmp_path, num_tx=1, progress=False)
    assert not (tmp_path / "sim").exists()


def test_reading_a_simulated_scene_compares_its_settings(small_room_root, compose_cfg):
    assert len(_scene(compose_cfg).load(small_room_root, BAND).ids) == 24
    # free text shapes nothing: the file is read
    assert len(_scene(compose_cfg, "scene.small_room.description=other").load(small_room_root, BAND).ids) == 24
    moved = _scene(compose_cfg, "scene.small_room.gateway.position=[1.0,1.0,1.5]")
    with pytest.raises(DataFormatError, match=r"scene.small_room.gateway.position: \[0.15, 1.5, 1.5\] in the file"):
        moved.load(small_room_root, BAND)
    # graf-train and graf-eval read it the same way (the datamodule loads every scene)
    cfg = compose_cfg(
        "eval",
        (
            "model=knn",
            "scene=small_room",
            "scene.small_room.num_tx=24",
            "scene.small_room.tracing.max_depth=5",
            f"data_root={small_room_root}",
        ),
    )
    with pytest.raises(DataFormatError, match="scene.small_room.tracing.max_depth: 3 in the file, 5 asked") as err:
        build_datamodule(cfg)[-1].setup("fit")
    assert is_user_error(err.value)


# ---------------------------------------------------------------------------------------------- B. a whole file


def _rewrite(h5: Path, key: str, values) -> None:
    with h5py.File(h5, "r+") as f:
        del f[key]
        f.create_dataset(key, data=np.asarray(values, dtype=np.int64))


@pytest.mark.parametrize(
    ("key", "values", "says"),
    [
        ("ids", np.arange(1, 31), "24 spectra but 30 ids"),
        ("ids", np.arange(0, 24), "ids must be integers from 1"),
        ("ids", [1, *range(1, 24)], "spectrum id 1 appears 2 times in 'ids'"),
        ("test_idx", [3, 99], "test_idx holds row 99, but the file has 24 spectra (rows 0-23)"),
        ("test_idx", [], "test_idx is empty: no spectrum to test on"),
        ("train_idx", [-1, 2], "train_idx holds row -1"),
        ("test_idx", "overlap", "are in both train_idx and test_idx"),
        ("test_idx", [5, 5], "test_idx lists row 5 twice"),
    ],
)
def test_a_dataset_whose_arrays_disagree_is_refused_naming_the_file(small_room_root, tmp_path, key, values, says):
    h5 = _copy(small_room_root, tmp_path) / "sim" / "small_room" / NAME
    if isinstance(values, str):  # two training rows listed for testing too
        with h5py.File(h5, "r") as f:
            train, test = f["train_idx"][()].tolist(), f["test_idx"][()].tolist()
        values, says = [*train[:2], *test], f"rows {train[:2]} {says}"
    _rewrite(h5, key, values)
    with pytest.raises(DataFormatError) as err:
        read_dataset(h5)
    assert str(err.value).startswith(f"{h5}: ") and says in str(err.value), str(err.value)


def test_a_truncated_file_is_refused_by_graf_simulate_and_by_readers_and_kept(small_room_root, tmp_path):
    root = _copy(small_room_root, tmp_path)
    h5 = root / "sim" / "small_room" / NAME
    os.truncate(h5, h5.stat().st_size // 2)
    cut = h5.read_bytes()
    line = _one_line_error(_simulate(root, tmp_path / "out"))
    assert str(h5) in line and "truncated" in line and "delete it" in line and "sim.overwrite=true" in line, line
    assert h5.read_bytes() == cut  # never deleted silently
    with pytest.raises(DataFormatError, match="unreadable.*truncated"):
        read_dataset(h5)


def test_a_damaged_file_is_refused_by_graf_simulate_and_by_readers(small_room_root, tmp_path, compose_cfg):
    from graf.sim.dataset import generate

    h5 = _copy(small_room_root, tmp_path) / "sim" / "small_room" / NAME
    with h5py.File(h5, "r") as f:
        chunk = f["spectra"].id.get_chunk_info(0)
    data = bytearray(h5.read_bytes())
    middle = chunk.byte_offset + chunk.size // 2
    data[middle : middle + 2000] = bytes(2000)  # a compressed chunk of spectra zeroed: HDF5 still opens the file
    h5.write_bytes(bytes(data))
    with pytest.raises(DataFormatError, match="is damaged: its spectra cannot be read"):
        read_dataset(h5)
    with pytest.raises(DataFormatError, match="is damaged: its spectra cannot be read .*sim.overwrite=true"):
        generate(_scene(compose_cfg), BAND, h5.parents[2], num_tx=24, progress=False)  # not skipped as there
    assert h5.read_bytes() == bytes(data)


def _drop_recorded(h5: Path, *where: str) -> None:
    with h5py.File(h5, "r+") as f:
        config = json.loads(f.attrs["config"])
        node = config
        for k in where[:-1]:
            node = node[k]
        del node[where[-1]]
        f.attrs["config"] = json.dumps(config, sort_keys=True)


def test_a_file_that_does_not_record_a_setting_is_refused_unless_its_value_then_is_known(
    small_room_root, tmp_path, compose_cfg, monkeypatch
):
    """A setting added to the scene configs after a file was written: the file does not record it, so what made
    the file is unknown (refused), unless RECORDED_SINCE gives the value files made before it used."""
    root = _copy(small_room_root, tmp_path)
    h5 = root / "sim" / "small_room" / NAME
    _drop_recorded(h5, "scene", "array", "hemisphere")
    with pytest.raises(DataFormatError, match="scene.small_room.array.hemisphere: absent in the file, 'front' asked"):
        _scene(compose_cfg).load(root, BAND)
    monkeypatch.setitem(checks.RECORDED_SINCE, ("scene", "array", "hemisphere"), "front")
    assert len(_scene(compose_cfg).load(root, BAND).ids) == 24
    with h5py.File(h5, "r+") as f:
        del f.attrs["config"]
    with pytest.raises(DataFormatError, match="has no 'config' attribute"):
        read_dataset(h5)
