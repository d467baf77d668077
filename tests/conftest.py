from __future__ import annotations

import os
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from graf.app.config import CONF_DIR
from graf.data.nerf2_format import write_nerf2_folder

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")
# graf-curves' checkpoints (checkpoint_root) go to a folder of the test run, not to the user's ~/.cache/graf
os.environ.setdefault("GRAF_CHECKPOINTS", tempfile.mkdtemp(prefix="graf-test-checkpoints-"))
if os.environ.get("PYTEST_XDIST_WORKER"):  # pytest -n 2: one core per worker, for its own work and its subprocesses
    os.environ["OMP_NUM_THREADS"] = "1"  # (two workers of two threads each on two cores slow each other many times)
    import torch

    torch.set_num_threads(1)


@pytest.fixture
def one_torch_thread():
    """One intra-op torch thread for the test, the caller's count restored after: small tensors run faster on one
    thread than with OpenMP barrier waits on a shared CPU (a 2,048-point NeRF2 training step took 16 ms on one
    thread and 1.4 s on two while other jobs loaded both cores)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


EMBEDDED_S23 = Path(__file__).resolve().parents[1] / "src" / "graf" / "embedded" / "rfid_s23_200"


def smooth_spectra(positions: np.ndarray, seed: int = 0) -> np.ndarray:
    """Spectra that vary smoothly with the transmitter position: a lobe whose direction follows it."""
    el = np.arange(1, 91)[None, :, None]
    az = np.arange(1, 361)[None, None, :]
    p = np.asarray(positions)
    az0 = (np.degrees(np.arctan2(p[:, 1], p[:, 0])) % 360)[:, None, None]
    el0 = (20 + 10 * p[:, 2])[:, None, None]
    daz = (az - az0 + 180) % 360 - 180
    s = np.exp(-((daz / 25.0) ** 2) - ((el - el0) / 15.0) ** 2)
    s = (s - s.min(axis=(1, 2), keepdims=True)) / np.ptp(s, axis=(1, 2), keepdims=True)
    return s.astype(np.float32)


@pytest.fixture(autouse=True)
def _sigint_put_back():
    """A test whose command ended on a Ctrl+C leaves SIGINT ignored in the worker (a second Ctrl+C is ignored
    while a command ends); put it back, or every subprocess the worker starts later inherits SIGINT ignored."""
    handler = signal.getsignal(signal.SIGINT)
    yield
    if signal.getsignal(signal.SIGINT) is not handler:
        signal.signal(signal.SIGINT, handler)


@pytest.fixture
def make_scene(tmp_path):
    """Write a tiny NeRF2-format scene; returns its folder."""

    def _make(n: int = 16, name: str = "tiny", index: bool = True, seed: int = 0) -> Path:
        rng = np.random.default_rng(seed)
        pos = rng.uniform([-1.0, 0.5, 0.0], [1.0, 1.5, 1.0], size=(n, 3))
        ids = np.arange(1, n + 1)
        n_train = int(n * 0.75)
        return write_nerf2_folder(
            tmp_path / name,
            smooth_spectra(pos),
            pos,
            ids,
            np.array([0.0, 0.0, 0.5]),
            np.array([0.0, 0.0, 0.0, 1.0]),
            train_ids=ids[:n_train] if index else None,
            test_ids=ids[n_train:] if index else None,
        )

    return _make


@pytest.fixture
def compose_cfg(tmp_path):
    """Compose the real configs (train or eval) with overrides; output folder in tmp_path."""

    def _compose(config_name: str = "eval", overrides: tuple[str, ...] = ()):
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(
                config_name=config_name,
                overrides=[
                    f"paths.output_dir={tmp_path / 'out'}",
                    "trainer.accelerator=cpu",
                    "logger=none",
                    "trainer.enable_progress_bar=false",
                    f"data_root={tmp_path / 'data'}",
                    *overrides,
                ],
            )
        GlobalHydra.instance().clear()
        return cfg

    return _compose


@pytest.fixture(scope="session")
def small_room_root(tmp_path_factory):
    """A data_root holding 24 ray-traced positions of small_room at 2.4 GHz (graf-simulate's code):
    ``scene.small_room.num_tx=24`` (or ``sim_num_tx=24``) reads them."""
    from graf.sim.simulate import simulate

    root = tmp_path_factory.mktemp("data")
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            "simulate",
            [
                "scene=small_room",
                "band=2.4ghz",
                "sim.num_tx=24",
                f"data_root={root}",
                f"paths.output_dir={root / 'sim_out'}",
                "sim.progress=false",
            ],
        )
    GlobalHydra.instance().clear()
    simulate(cfg)
    return root


@pytest.fixture(scope="session")
def postgres():
    """A PostgreSQL server of the tests' own (tests/postgres.py); skipped, with the reason, where it cannot start."""
    from tests.postgres import PostgresServer

    server = PostgresServer()
    reason = server.start()
    if reason is not None:
        server.stop()
        pytest.skip(reason)
    yield server
    server.stop()
