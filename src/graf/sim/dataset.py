"""Dataset files of simulated scenes: resumable generation and reading.

One HDF5 file per (scene, band): ``<data_root>/sim/<scene>/<band>[-n<N>].h5``.  HDF5 because it is one
self-describing file with chunked, compressed arrays and attributes that numpy, MATLAB and h5py users
read without our code; zarr would make thousands of small files and add a format still in flux.

    spectra     uint8 [N, 90, 360]   pixel = round(255 * min-max normalised Bartlett amplitude), as NeRF2's PNGs
    channels    complex64 [N, 16]    per-antenna channel h (the spectra are an exact function of it)
    positions   float64 [N, 3]       transmitter positions (m)
    ids         int64 [N]            1..N (id k = row k-1, as NeRF2)
    num_paths   int32 [N]            valid traced paths per position
    train_idx / test_idx  int64      seeded split (row indices)
    antenna_positions float64 [16,3] in the gateway frame
    attrs: scene, band, frequency_hz, wavelength, gateway_position, gateway_orientation (x,y,z,w),
           bounds [2,3], angle_convention, config (JSON of the full generating config), versions

Generation writes chunks of ``chunk_size`` spectra as separate files (atomically) under
``<file>.parts/``; a killed run, started again with the same command, skips finished chunks, so no
spectrum is lost or made twice.  When every chunk is there, the HDF5 file is assembled in a temporary
file and renamed into place.  A changed configuration is refused: the parts carry its fingerprint, and the file
records it, compared with the asked one by every later run and every read (:mod:`graf.sim.checks`).

**Shards.**  ``shard=(i, n)`` traces only the i-th of n contiguous ranges of chunks (so of transmitter
positions), one process or machine per shard sharing ``data_root``; each shard is resumable on its own.  The
shard that finds every chunk there when it ends assembles the file (under an exclusive lock, so two shards
finishing together do not both write it); ``merge_only=True`` assembles it explicitly (after a shard was killed
while assembling, say) and names the missing chunks if there are any.  The chunks, and so the file, are the
same as a single process's: the merged file equals it byte for byte.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from pathlib import Path

import h5py
import numpy as np
import torch
from tqdm.auto import tqdm

import graf
from graf.bands import Band
from graf.data.nerf2_format import write_nerf2_folder
from graf.data.spectrum_set import DataFormatError, SpectrumSet, warn_flat_spectra
from graf.errors import ConfigError
from graf.geometry.grid import SPECTRUM_SHAPE
from graf.io import atomic_write_json, atomic_write_npz
from graf.sim.array import to_uint8
from graf.sim.checks import check_arrays, compare_config, open_dataset, read_spectra, stored_config

log = logging.getLogger(__name__)
FORMAT_VERSION = 1
ANGLE_CONVENTION = (
    "row r = elevation r+1 deg, column c = azimuth c+1 deg; direction (cos e cos a, cos e sin a, "
    "sin e) in the gateway frame (array in z=0, facing +z); rows cover the front hemisphere"
)
SIMULATE_REMEDY = (
    "to trace the asked settings, give another data_root, or run with sim.overwrite=true to replace this file (or "
    "delete it); to use this file, ask for the settings it was made with"
)


def fingerprint(config: dict) -> str:
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


def generate(
    scene,
    band: Band,
    data_root: str | Path,
    num_tx: int | None = None,
    chunk_size: int = 256,
    overwrite: bool = False,
    device: str = "cpu",
    progress: bool = True,
    shard: tuple[int, int] = (0, 1),
    merge_only: bool = False,
) -> dict:
    """Trace every transmitter position of ``scene`` at ``band`` (or shard ``i`` of ``n``: see the module doc) and
    write the dataset file.

    Returns a summary: path, n, seconds, spectra per second (of the spectra made in this call), whether the file
    was assembled, and the chunks still missing (other shards')."""
    started = time.perf_counter()
    path = scene.dataset_path(data_root, band, num_tx)
    parts = path.with_name(path.name + ".parts")
    positions = scene.positions(num_tx)
    n = len(positions)
    if n < 2:  # the split would leave nothing to train on, and the file would be refused on every read
        asked = f"sim.num_tx={num_tx}" if num_tx is not None else f"scene.{scene.name}.transmitters.count={n}"
        raise ConfigError(f"{asked}: a dataset needs at least 2 positions (one to train on, one to test)")
    config = dataset_config(scene, band, n, chunk_size)
    index, count = (int(v) for v in shard)
    check_shard(index, count, overwrite, merge_only, parts)
    if path.is_file() and not overwrite:  # the file is whole and made by these settings, or refused
        check_file(path, {k: v for k, v in config.items() if k != "format_version"}, scene.name, SIMULATE_REMEDY)
        log.info("%s exists; nothing to do (overwrite=true makes it again)", path)
        return {"path": str(path), "n": n, "made": 0, "seconds": 0.0, "spectra_per_second": None, "skipped": True}
    manifest = open_parts(path, parts, config, overwrite)
    chunks = [(i, s, min(s + chunk_size, n)) for i, s in enumerate(range(0, n, chunk_size))]
    mine = [] if merge_only else chunks[index * len(chunks) // count : (index + 1) * len(chunks) // count]
    made, t_trace, materials = trace_chunks(scene, band, positions, parts, mine, device, progress, started)
    materials = record_materials(manifest, materials)
    missing = missing_chunks(parts, chunks, merge_only)
    assembled = False
    if not missing and _lock(parts, force=merge_only):
        _assemble(path, parts, chunks, scene, band, positions, scene.antenna_positions(band), config, materials)
        shutil.rmtree(parts, ignore_errors=True)
        assembled = True
    seconds = time.perf_counter() - started
    return {
        "path": str(path),
        "n": n,
        "made": made,
        "seconds": round(seconds, 3),
        "spectra_per_second": round(made / seconds, 2) if made else None,
        "trace_seconds": round(t_trace, 3),
        "skipped": False,
        "materials": materials,
        "shard": [index, count],
        "shard_positions": [mine[0][1], mine[-1][2]] if mine else None,
        "assembled": assembled,
        "missing_chunks": len(missing),
    }


def dataset_config(scene, band: Band, n: int, chunk_size: int) -> dict:
    """What makes a dataset file: its fingerprint (:func:`fingerprint`) guards the parts of a resumed run, and the
    file records it (compared on every later run and read: :mod:`graf.sim.checks`)."""
    return {**scene_config(scene, band, n), "chunk_size": int(chunk_size), "format_version": FORMAT_VERSION}


def scene_config(scene, band: Band, n: int) -> dict:
    """The part of :func:`dataset_config` a scene's reader knows: the scene's config, the band, ``n`` positions."""
    return {"scene": scene.config(), "band": {"name": band.name, "frequency_hz": band.frequency_hz}, "num_tx": n}


def check_file(path: Path, asked: dict, scene_key: str, remedy: str) -> None:
    """Refuse a dataset file that is unreadable or damaged, whose arrays disagree, or that was made by other settings
    than ``asked`` (:mod:`graf.sim.checks`): it reads every spectrum once, so a damaged chunk is not taken as done."""
    with open_dataset(path) as f:
        check_arrays(path, f)
        compare_config(path, stored_config(path, f), asked, scene_key, remedy)
        read_spectra(path, f)


def record_materials(manifest: Path, materials: list | None) -> list:
    """The traced materials, recorded in the manifest; None (nothing traced in this call): the ones recorded."""
    if materials is None:
        return json.loads(manifest.read_text()).get("materials", [])
    atomic_write_json(manifest, {**json.loads(manifest.read_text()), "materials": materials})
    return materials


def missing_chunks(parts: Path, chunks: list[tuple[int, int, int]], merge_only: bool) -> list[int]:
    """The chunks not yet in ``parts`` (an explicit merge refuses any)."""
    missing = [i for i, _, _ in chunks if not (parts / f"chunk_{i:05d}.npz").is_file()]
    if merge_only and missing:
        _, start, end = chunks[missing[0]]
        raise DataFormatError(
            parts,
            f"{len(missing)} of {len(chunks)} chunks are missing (first: chunk_{missing[0]:05d}, positions "
            f"{start}-{end - 1}): run their shards first",
        )
    return missing


def check_shard(index: int, count: int, overwrite: bool, merge_only: bool, parts: Path) -> None:
    """Refuse a shard ``index`` outside ``0 .. count - 1``, and ``overwrite`` with shards or a merge."""
    if count < 1 or not 0 <= index < count:
        raise ConfigError(f"sim.shard: index {index} of count {count}; need count >= 1 and 0 <= index < count")
    if overwrite and (count > 1 or merge_only):
        raise ConfigError(
            "sim.overwrite with shards or a merge would delete other shards' chunks: remove the file and its "
            f"{parts.name} folder once, then run the shards"
        )


def open_parts(path: Path, parts: Path, config: dict, overwrite: bool) -> Path:
    """The parts folder's manifest, made for ``config`` (after removing the file and its parts on ``overwrite``);
    chunks of another configuration there are refused."""
    if overwrite:
        path.unlink(missing_ok=True)
        shutil.rmtree(parts, ignore_errors=True)
    parts.mkdir(parents=True, exist_ok=True)
    manifest = parts / "manifest.json"
    fp = fingerprint(config)
    if manifest.is_file():
        old = json.loads(manifest.read_text())
        if old.get("fingerprint") != fp:
            raise DataFormatError(
                parts,
                "holds chunks of a different configuration; run with sim.overwrite=true "
                "to start again (or restore the configuration that made them)",
            )
    else:
        atomic_write_json(manifest, {"fingerprint": fp, "config": config})
    return manifest


def trace_chunks(scene, band: Band, positions, parts: Path, mine, device: str, progress: bool, started: float):
    """Trace the chunks ``mine`` (``(i, start, end)``) not yet in ``parts``, each written atomically.  Returns
    ``(spectra made, seconds tracing, the tracer's material table or None when nothing was traced)``."""
    todo = [c for c in mine if not (parts / f"chunk_{c[0]:05d}.npz").is_file()]
    done_before = sum(e - s for i, s, e in mine if (i, s, e) not in todo)
    made, t_trace, tracer = 0, 0.0, None
    bar = tqdm(
        total=sum(e - s for _, s, e in mine),
        initial=done_before,
        unit="spectra",
        desc=f"{scene.name} {band.name}",
        disable=not progress,
        dynamic_ncols=True,
    )
    if todo:
        tracer = scene.tracer(band)
        bartlett = scene.bartlett(band, device=device)
        for i, s, e in todo:
            t0 = time.perf_counter()
            h, spectra, counts = scene.spectra(tracer, bartlett, positions[s:e])
            atomic_write_npz(
                parts / f"chunk_{i:05d}.npz",
                spectra=to_uint8(spectra),
                channels=h.cpu().numpy().astype(np.complex64),
                num_paths=counts.astype(np.int32),
            )
            t_trace += time.perf_counter() - t0
            made += e - s
            bar.update(e - s)
            bar.set_postfix(spectra_per_s=f"{made / max(time.perf_counter() - started, 1e-9):.1f}")
    bar.close()
    return made, t_trace, (tracer.material_table() if tracer is not None else None)


def _lock(parts: Path, force: bool = False) -> bool:
    """Take the right to assemble (an exclusive lock file in the parts folder): False if another shard holds it.
    ``force`` (an explicit merge) takes it whatever a killed shard left."""
    lock = parts / "assemble.lock"
    if force:
        lock.unlink(missing_ok=True)
    try:
        os.close(os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        log.info("%s: another shard is assembling the file", parts)
        return False
    return True


def _assemble(path: Path, parts: Path, chunks, scene, band: Band, positions, antennas, config, materials) -> None:
    spectra = np.concatenate([np.load(parts / f"chunk_{i:05d}.npz")["spectra"] for i, _, _ in chunks])
    channels = np.concatenate([np.load(parts / f"chunk_{i:05d}.npz")["channels"] for i, _, _ in chunks])
    num_paths = np.concatenate([np.load(parts / f"chunk_{i:05d}.npz")["num_paths"] for i, _, _ in chunks])
    n = len(positions)
    if len(spectra) != n:
        raise DataFormatError(parts, f"chunks hold {len(spectra)} spectra, expected {n}")
    train_idx, test_idx = scene.split(n)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # two runs tracing one scene never share it
    with h5py.File(tmp, "w", track_order=False) as f:
        kw = dict(track_times=False)
        f.create_dataset(
            "spectra",
            data=spectra,
            chunks=(min(64, n), *SPECTRUM_SHAPE),
            compression="gzip",
            compression_opts=4,
            shuffle=True,
            **kw,
        )
        f.create_dataset("channels", data=channels, **kw)
        f.create_dataset("positions", data=positions.astype(np.float64), **kw)
        f.create_dataset("ids", data=np.arange(1, n + 1, dtype=np.int64), **kw)
        f.create_dataset("num_paths", data=num_paths, **kw)
        f.create_dataset("train_idx", data=train_idx.astype(np.int64), **kw)
        f.create_dataset("test_idx", data=test_idx.astype(np.int64), **kw)
        f.create_dataset("antenna_positions", data=antennas, **kw)
        a = f.attrs
        a["format_version"] = FORMAT_VERSION
        a["scene"] = scene.name
        a["band"] = band.name
        a["frequency_hz"] = band.frequency_hz
        a["wavelength"] = band.wavelength
        a["gateway_position"] = np.asarray(scene.gateway["position"], float)
        a["gateway_orientation"] = scene.rotation.as_quat()  # x, y, z, w
        a["bounds"] = scene.geometry.bounds
        a["angle_convention"] = ANGLE_CONVENTION
        a["config"] = json.dumps(config, sort_keys=True, default=str)
        a["materials"] = json.dumps(materials, sort_keys=True, default=str)
        a["graf_version"] = graf.__version__
    tmp.replace(path)


def read_dataset(path: str | Path, name: str | None = None) -> SpectrumSet:
    """A simulated scene's dataset file as a :class:`SpectrumSet` (spectra = uint8 / 255), after the checks of
    its arrays (:func:`graf.sim.checks.check_arrays`); what made it is compared by the scene's reader."""
    path = Path(path)
    with open_dataset(path) as f:
        check_arrays(path, f)
        config = stored_config(path, f)
        positions = f["positions"][()]
        if not np.isfinite(positions).all():
            raise DataFormatError(path, "positions are not all finite")
        a = dict(f.attrs)
        ids = f["ids"][()].astype(np.int64)
        spectra = torch.from_numpy(read_spectra(path, f)).float().div_(255.0)
        warn_flat_spectra(spectra, ids, path)
        return SpectrumSet(
            name=name or str(a.get("scene", path.stem)),
            spectra=spectra,
            positions=positions,
            ids=ids,
            train_idx=f["train_idx"][()].astype(np.int64),
            test_idx=f["test_idx"][()].astype(np.int64),
            gateway_position=np.asarray(a["gateway_position"], float),
            gateway_orientation=np.asarray(a["gateway_orientation"], float),
            frequency_hz=float(a["frequency_hz"]),
            source=str(path),
            split_source="seeded split stored in the dataset file",
            meta={
                "bounds": np.asarray(a["bounds"], float).tolist(),
                "config": config,
                "num_paths": f["num_paths"][()] if "num_paths" in f else None,
            },
        )


def export_nerf2(dataset_path: str | Path, out_dir: str | Path) -> Path:
    """Write a dataset file as a NeRF2 folder (PNG spectra are the stored uint8 values, so
    :func:`graf.data.nerf2_format.read_nerf2_folder` reads back the same spectra)."""
    d = read_dataset(dataset_path)
    return write_nerf2_folder(
        out_dir,
        d.spectra,
        d.positions,
        d.ids,
        d.gateway_position,
        d.gateway_orientation,
        train_ids=d.ids[d.train_idx],
        test_ids=d.ids[d.test_idx],
    )
