"""Multi-head attention with a backward through the compiled kernel (``attention_cpu.cpp``): GRaF's training on a CPU.

GRaF's attention is many short sequences (a ray's voxels, a ray's L neighbor tokens) of narrow heads (10 of 8, 1 of
16).  Through torch, a training step spends most of its attention time moving data: the heads are transposed out
of the projections and back (``copy_``), and the scores ``[n, H, S, S]`` are written, soft-maxed, written again and
read back by the backward.  The kernel reads the projections where they are (token-major ``[G, S, H, Dh]``, any
strides with the feature axis contiguous), keeps 16 queries' scores in registers and stores only the output and
each query's maximum score and softmax denominator; the backward recomputes the probabilities from them
(as flash attention does).

Each group (a ray) is computed whole by one call, so the result does not depend on how the groups are split over
threads: the same bits for any thread count.  The groups are spread over ``torch.get_num_threads()`` worker threads
(ctypes releases the GIL), in more pieces than threads so that a thread slowed by another process holds up only a
small piece.
"""

from __future__ import annotations

import ctypes
from concurrent.futures import ThreadPoolExecutor

import torch

from graf.models.graf.kernels import native

PIECES_PER_THREAD = 4  # pieces of the groups per worker thread (load balance beside other processes)
_pools: dict[int, ThreadPoolExecutor] = {}


def worker_pool(workers: int) -> ThreadPoolExecutor:
    """One pool of ``workers`` threads per size, kept for the process (the kernel's groups, GRaF's pieces)."""
    if workers not in _pools:
        _pools[workers] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="graf-worker")
    return _pools[workers]


def _spread(call, groups: int) -> None:
    """``call(g0, g1)`` over ``[0, groups)`` in pieces on the worker threads (in this thread when there is one)."""
    workers = max(1, torch.get_num_threads())
    if workers == 1 or groups < 2 * workers:
        call(0, groups)
        return
    per = -(-groups // (workers * PIECES_PER_THREAD))
    bounds = list(range(0, groups, per)) + [groups]
    list(worker_pool(workers).map(lambda i: call(bounds[i], bounds[i + 1]), range(len(bounds) - 1)))


def supported(q: torch.Tensor, kv: torch.Tensor | None, heads: int, head_dim: int, mask: torch.Tensor | None) -> bool:
    """Whether :func:`attention` takes these operands on this machine: contiguous float32 CPU projections (``q``:
    ``[G, S, 3 H Dh]`` of a self-attention, or ``[G, Sq, H Dh]`` with ``kv [G, Sk, 2 H Dh]``), a mask ``[G or 1,
    keys]`` or None, ``Dh`` and the keys within the kernel's limits, no autocast."""
    lib = native.library()
    if lib is None or torch.is_autocast_enabled("cpu"):
        return False
    HD = heads * head_dim
    parts = [(q, 3 * HD if kv is None else HD)] + ([] if kv is None else [(kv, 2 * HD)])
    for t, width in parts:
        if t.dim() != 3 or t.dtype != torch.float32 or t.device.type != "cpu" or not t.is_contiguous():
            return False
        if t.shape[-1] != width or t.shape[0] != q.shape[0]:
            return False
    keys = q.shape[1] if kv is None else kv.shape[1]
    if mask is not None and (mask.dim() != 2 or mask.shape[-1] != keys or mask.shape[0] not in (1, q.shape[0])):
        return False
    return head_dim <= lib.graf_attention_max_dim() and keys <= lib.graf_attention_max_keys()


def _args(q: torch.Tensor, kv: torch.Tensor | None, H: int, Dh: int, mask, scale: float) -> native.AttnArgs:
    """The kernel's operands: q, k and v inside the projections (k and v of a self-attention in ``q``'s rows)."""
    HD = H * Dh
    src, k_at, v_at = (q, HD, 2 * HD) if kv is None else (kv, 0, HD)
    ptr = lambda t, off: t.data_ptr() + off * t.element_size()  # noqa: E731
    a = native.AttnArgs(q.data_ptr(), ptr(src, k_at), ptr(src, v_at), None if mask is None else mask.data_ptr())
    a.qg, a.qs, a.qh = q.stride(0), q.stride(1), Dh
    a.kg, a.ks, a.kh = src.stride(0), src.stride(1), Dh
    a.vg, a.vs, a.vh = a.kg, a.ks, Dh
    a.mask_stride = 0 if mask is None or mask.shape[0] == 1 else mask.stride(0)
    a.H, a.Dh, a.Sq, a.Sk, a.scale = H, Dh, q.shape[1], src.shape[1], float(scale)
    a.dqs, a.dks = q.shape[2], src.shape[2]
    return a


class _Attention(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, kv, mask, H, Dh, scale):
        lib = native.library()
        G, Sq = q.shape[:2]
        o = torch.empty(G, Sq, H, Dh, dtype=torch.float32)
        lse = torch.empty(G, H, 2, Sq, dtype=torch.float32)  # per row: the maximum score, 1 / the denominator
        args = _args(q, kv, H, Dh, mask, scale)
        ref = ctypes.byref(args)
        _spread(lambda g0, g1: lib.graf_attn_train_fwd(ref, o.data_ptr(), lse.data_ptr(), g0, g1), G)
        ctx.save_for_backward(q, kv, o, lse)
        ctx.mask, ctx.shape = mask, (H, Dh, scale)
        return o

    @staticmethod
    def backward(ctx, dout):
        lib = native.library()
        q, kv, o, lse = ctx.saved_tensors
        H, Dh, scale = ctx.shape
        dout = dout.contiguous()
        args = _args(q, kv, H, Dh, ctx.mask, scale)
        dq = torch.empty_like(q)  # self-attention: dq, dk and dv interleaved as q, k and v are
        dkv = None if kv is None else torch.empty_like(kv)
        at = lambda t, off: t.data_ptr() + off * t.element_size()  # noqa: E731
        HD = H * Dh
        dk, dv = (at(dq, HD), at(dq, 2 * HD)) if kv is None else (at(dkv, 0), at(dkv, HD))
        ptrs = (o.data_ptr(), lse.data_ptr(), dout.data_ptr(), dq.data_ptr(), dk, dv)
        ref = ctypes.byref(args)
        _spread(lambda g0, g1: lib.graf_attn_train_bwd(ref, *ptrs, g0, g1), q.shape[0])
        return dq, dkv, None, None, None, None


def attention(
    q: torch.Tensor, kv: torch.Tensor | None, heads: int, head_dim: int, mask: torch.Tensor | None, scale: float
) -> torch.Tensor:
    """``softmax(scale q k^T) v`` per group and head, differentiable, from the projections as they come out of
    their linear layers: a self-attention's ``q [G, S, 3 H Dh]`` (rows: q, k, v, each head-major) and ``kv`` None,
    or a cross-attention's ``q [G, Sq, H Dh]`` and ``kv [G, Sk, 2 H Dh]`` (rows: k, v).  Key ``mask [G or 1, Sk]``
    (True = attend; at least one per group) or None.  -> ``[G, Sq, H, Dh]`` (contiguous).  Only where
    :func:`supported` says so."""
    if mask is not None:
        mask = mask.to(torch.uint8).contiguous()
    return _Attention.apply(q, kv, mask, heads, head_dim, scale)
