"""How GRaF's Transformer blocks run, and how a whole spectrum's chunks of rays are spread over the CPU's cores.

**Fast path** (:func:`fast_path`): at inference on a CPU in fp32 (eval mode, no autograd, no autocast, the
model's ``fast_inference`` on) the blocks run feature-major through :mod:`graf.models.graf.kernels` (a fused
attention kernel): the same function within float rounding (tests/models/test_graf_fast.py).  Everywhere else (training,
GPUs, reduced precision) the blocks' own ``forward`` runs: the *plain path*.

**Chunks in parallel** (:func:`map_chunks`): on a CPU, a spectrum's chunks of rays go to ``torch.get_num_threads()``
worker threads, each running its chunk's operations on one thread (torch's intra-op threads set to 1 meanwhile).
GRaF's operations are many and small (width 16), so splitting each one over threads costs a synchronisation per
operation; with another process on the machine one thread of each operation waits for a time slice and every
operation waits for it (GRaF slowed 30x beside one busy process).  Whole chunks per thread need no
synchronisation but the end: quiet, about as fast; beside a busy process, slowed as much as the lost core.
What still runs on torch's intra-op threads (the neighbor encoder, the first slice of rays that fills the
evaluation caches) gets the cores the other processes leave free (:func:`serial_threads`: their load read from
``/proc`` by :class:`graf.machine.LoadMonitor`), never more than the threads set.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import torch
from torch import nn

from graf.machine import available_cores, monitor, threads_beside_load
from graf.models.graf.kernels import native
from graf.models.graf.kernels.blocks import fusable, mlp_fusable, ray_pass_weights, run_blocks

FAST_PIECE_VOXELS = 4096  # voxels per piece through the ray transformer on the fast path (stays in cache)
log = logging.getLogger("graf")
_told: list = []  # the thread reduction is logged once per process


def fast_path(enabled: bool, training: bool, x: torch.Tensor) -> bool:
    """Whether the blocks take the fast path for ``x`` (see module doc)."""
    return (
        enabled
        and not training
        and not torch.is_grad_enabled()
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and not torch.is_autocast_enabled("cpu")
    )


def scene_blocks(
    blocks: nn.ModuleList, x: torch.Tensor, tokens: torch.Tensor, key_mask: torch.Tensor | None, fast: bool
) -> torch.Tensor:
    """The cross-attention blocks: queries ``x [B, N, d]`` over ``tokens [B, L, d]``."""
    if fast:
        return run_blocks(blocks, x, tokens, key_mask)
    for blk in blocks:
        x = blk(x, tokens, key_mask)
    return x


def _self_blocks(blocks: nn.ModuleList, v: torch.Tensor, fast: bool, mask: torch.Tensor | None = None) -> torch.Tensor:
    if not fast:
        for blk in blocks:
            v = blk(v, mask)
        return v
    per = max(1, FAST_PIECE_VOXELS // v.shape[1])
    pieces = [run_blocks(blocks, piece) for piece in v.split(per)]  # each piece through every block in cache
    return pieces[0] if len(pieces) == 1 else torch.cat(pieces)


def ray_transformer(
    blocks: nn.ModuleList, v: torch.Tensor, window: int, fast: bool, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """The ray blocks over ``v [n, S, d]``: full self-attention along the ray, or, with ``window`` W and S > W,
    attention within consecutive windows of W voxels (the last window holds the remainder).  ``mask [n, S]``
    (padded rays, full attention only): True for each ray's own voxels, the only keys attended to."""
    n, S, d = v.shape
    if not window or S <= window:
        return _self_blocks(blocks, v, fast, mask)
    if mask is not None:
        raise ValueError("padded rays need attention over the whole ray (model.ray_window 0 or >= S)")
    k = S // window
    if fast:  # every block on the windows: the blocks are per window, so the windows can go through all at once
        head = _self_blocks(blocks, v[:, : k * window].reshape(n * k, window, d), fast).reshape(n, k * window, d)
        return head if k * window == S else torch.cat([head, _self_blocks(blocks, v[:, k * window :], fast)], dim=1)
    for blk in blocks:
        head = blk(v[:, : k * window].reshape(n * k, window, d)).view(n, k * window, d)
        v = head if k * window == S else torch.cat([head, blk(v[:, k * window :])], dim=1)
    return v


def ray_pass(
    model: nn.Module,
    x: torch.Tensor,
    tokens: torch.Tensor,
    key_mask,
    code: torch.Tensor,
    fast: bool,
    voxels: torch.Tensor | None = None,
):
    """GRaF's rays from their voxel queries to their pooled state ``[n, d]``: the scene blocks (queries ``x [n, S,
    d]`` over ``tokens [n or 1, L, d]``), MLP2 plus the voxels' distance ``code [n, S, d]``, the ray transformer,
    the mean over each ray.  ``voxels [n, S]`` (rays padded to S, :mod:`graf.models.graf.buckets`): True for each
    ray's own voxels; the padding is left out of the ray transformer's keys and of the mean.  On the fast path
    with the compiled kernels, all of it feature-major on pieces of :data:`FAST_PIECE_VOXELS` voxels (each piece
    through every stage while it is in cache, MLP2's hidden layer never in memory: :func:`fused_ray_pass`)."""
    n, S, d = code.shape
    if voxels is not None:
        x = scene_blocks(model.scene_blocks, x, tokens, key_mask, False)
        v = ray_transformer(model.ray_blocks, model.mlp2(x).view(n, S, d) + code, model.ray_window, False, voxels)
        w = voxels.to(v.dtype)[..., None]
        return ((v * w).sum(dim=1) / w.sum(dim=1)).float()
    if fast:
        # one long query axis over shared tokens (pooled): the scene blocks act per position, so per ray as well
        xr = x.view(n, S, d) if x.shape[:2] == (1, n * S) and tokens.shape[0] == 1 else x
        if _fused_ok(model, xr, tokens, n, S):
            return fused_ray_pass(model, xr, tokens, key_mask, code)
    x = scene_blocks(model.scene_blocks, x, tokens, key_mask, fast)
    v = model.mlp2(x).view(n, S, d) + code
    v = ray_transformer(model.ray_blocks, v, model.ray_window, fast)
    return v.float().mean(dim=1)


def _fused_ok(model: nn.Module, x: torch.Tensor, tokens: torch.Tensor, n: int, S: int) -> bool:
    return (
        x.shape[:2] == (n, S)
        and tokens.shape[0] in (1, n)
        and (not model.ray_window or S <= model.ray_window)
        and fusable(model.scene_blocks, tokens.shape[1])
        and fusable(model.ray_blocks, S)
        and mlp_fusable(model.mlp2)
    )


def fused_ray_pass(model: nn.Module, x: torch.Tensor, tokens: torch.Tensor, key_mask, code: torch.Tensor):
    """:func:`ray_pass` through the compiled kernels (where :func:`_fused_ok`): one ray at a time, every stage
    while the ray is in cache (:func:`graf.models.graf.kernels.native.ray_pass`)."""
    return native.ray_pass(ray_pass_weights(model), x, tokens, key_mask, code)


def serial_threads(threads: int | None = None) -> int:
    """torch threads for a spectrum's serial phases: ``threads`` (default ``torch.get_num_threads()``) less the
    cores other processes are using (:func:`graf.machine.threads_beside_load`: measured from CPU time; rounded), at
    least 1; ``threads`` while they use less than :data:`graf.machine.BUSY_CORES` (a different thread count can
    change a result's last bits: a quiet machine keeps one)."""
    threads = torch.get_num_threads() if threads is None else int(threads)
    fewer, other = threads_beside_load(threads)
    if fewer < threads and not _told:
        _told.append(True)
        log.info(
            "measured: other processes used %.2f of %d cores in each of the last two half-second windows (%.1f s of "
            "CPU time read from /proc; this process and its children left out): GRaF's encoder runs on %d of the %d "
            "threads set (once told)",
            other,
            available_cores(),
            monitor().window_s(),
            fewer,
            threads,
        )
    return fewer


class SerialThreads:
    """``with SerialThreads(device):`` torch's intra-op threads at :func:`serial_threads` (CPU only), restored after;
    :func:`split_batch` inside still spreads its batch over the threads set before."""

    outer: int | None = None  # the threads set outside the innermost SerialThreads in force

    def __init__(self, device: torch.device):
        self.device = device

    def __enter__(self):
        self.threads, self.before = torch.get_num_threads(), SerialThreads.outer
        SerialThreads.outer = self.threads
        if self.device.type == "cpu":
            torch.set_num_threads(serial_threads(self.threads))
        return self

    def __exit__(self, *exc):
        torch.set_num_threads(self.threads)
        SerialThreads.outer = self.before
        return False


def split_batch(fn: Callable, x: torch.Tensor) -> torch.Tensor:
    """``fn(x)`` for a batch ``x [N, ...]`` whose items are independent (the neighbor encoder): on a CPU without
    autograd or autocast, ``x`` split in one piece per thread set (:attr:`SerialThreads.outer`, else torch's),
    each piece on a worker thread at one intra-op thread (whole pieces per thread: beside a busy process each
    slows as much as its core, where one operation split over threads waits for the slowest); else at once."""
    workers = min(SerialThreads.outer or torch.get_num_threads(), x.shape[0])
    if x.device.type != "cpu" or workers <= 1 or torch.is_grad_enabled() or torch.is_autocast_enabled("cpu"):
        return fn(x)

    def run(piece):
        with torch.no_grad():
            return fn(piece)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="graf-batch") as pool:
            parts = list(pool.map(run, x.chunk(workers)))
    finally:
        torch.set_num_threads(threads)
    return torch.cat(parts)


def map_chunks(fn: Callable, items: Sequence, device: torch.device, workers: int | None = None) -> list:
    """``[fn(item) for item in items]``; on a CPU the first in this thread (it fills the model's evaluation
    caches), the rest spread over ``workers`` threads (default ``torch.get_num_threads()``) with torch's intra-op
    threads at 1 meanwhile (see module doc).  Only without autograd or autocast (both thread-local in torch);
    otherwise in order in this thread.  Results in order."""
    workers = torch.get_num_threads() if workers is None else int(workers)
    serial = torch.is_grad_enabled() or torch.is_autocast_enabled("cpu")  # thread-local modes: not carried over
    if device.type != "cpu" or workers <= 1 or len(items) <= 2 or serial:
        return [fn(item) for item in items]

    def run(item):
        with torch.no_grad():
            return fn(item)

    with SerialThreads(device):
        first = fn(items[0])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="graf-chunk") as pool:
            rest = list(pool.map(run, items[1:]))
    finally:
        torch.set_num_threads(threads)
    return [first, *rest]


def rays_in_chunks(render: Callable, order: torch.Tensor, chunk_rays: int) -> torch.Tensor:
    """``render(pixels [B, n]) -> [B, n]`` over all of ``order [B, P]`` in chunks of at most ``chunk_rays`` rays over
    the batch (memory bounded by the chunk), through :func:`map_chunks`: a first ray alone (it fills the evaluation
    caches), then the chunks on the worker threads.  ``[B, P]``."""
    B, P = order.shape
    per = max(1, chunk_rays // B)
    bounds = [0, 1, *range(1 + per, P, per), P]
    parts = map_chunks(lambda i: render(order[:, bounds[i] : bounds[i + 1]]), range(len(bounds) - 1), order.device)
    return torch.cat(parts, dim=1)
