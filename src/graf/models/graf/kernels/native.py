"""The compiled attention kernel (``attention_cpu.cpp`` beside this file), built at first use and called through
ctypes.

The source is compiled once per machine with the system's C++ compiler (``$CXX``, else ``c++``/``g++``:
``-O3 -march=native -fno-math-errno -shared -fPIC``; ``GRAF_KERNEL_VECTOR_BYTES`` 32 or 64 fixes the vector width,
else the CPU's widest) into ``$GRAF_KERNEL_DIR`` (default
``~/.cache/graf/kernels``), named by a hash of the source, the flags and the CPU, written atomically (two
processes building at once both succeed).  Where there is no compiler, or the build or the load fails, or
``GRAF_NATIVE_KERNELS=0``, :func:`library` returns None once with a warning and callers use their torch path
(the same arithmetic in torch operations).  No Python headers, no torch headers, no ninja: the library exports
plain C functions on raw float pointers.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import torch

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("attention_cpu.cpp")
FLAGS = ("-O3", "-march=native", "-fno-math-errno", "-shared", "-fPIC")
_lock = threading.Lock()
_state: dict = {}


def kernel_dir() -> Path:
    return Path(os.environ.get("GRAF_KERNEL_DIR") or Path.home() / ".cache" / "graf" / "kernels")


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _cpu_id() -> str:
    """What ``-march=native`` compiles for: the CPU's model name and flags (from /proc/cpuinfo where there is one)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        keep = [ln for ln in lines if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(keep) or platform.processor()
    except OSError:
        return platform.machine() + platform.processor()


def flags() -> tuple[str, ...]:
    """The compiler's flags: :data:`FLAGS`, and the vector width ``GRAF_KERNEL_VECTOR_BYTES`` (32 or 64) where it is
    set; unset, the source picks the CPU's widest (16 lanes with AVX-512, 8 with AVX2)."""
    width = os.environ.get("GRAF_KERNEL_VECTOR_BYTES", "")
    if width not in ("", "32", "64"):
        raise RuntimeError(f"GRAF_KERNEL_VECTOR_BYTES={width!r}: must be 32 or 64 (bytes per vector)")
    return FLAGS + ((f"-DGRAF_VECTOR_BYTES={width}",) if width else ())


def _build(cxx: str) -> Path:
    src = SOURCE.read_bytes()
    key = hashlib.sha256(src + " ".join((cxx,) + flags()).encode() + _cpu_id().encode()).hexdigest()[:16]
    out = kernel_dir() / f"graf_attention_{key}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        tmp_so = Path(tmp) / out.name
        proc = subprocess.run([cxx, *flags(), str(SOURCE), "-o", str(tmp_so)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{cxx} failed on {SOURCE}: {proc.stderr.strip()[-2000:]}")
        os.replace(tmp_so, out)  # atomic: a concurrent build of the same key writes the same bytes
    return out


def _load() -> ctypes.CDLL | None:
    if os.environ.get("GRAF_NATIVE_KERNELS", "1") == "0":
        return None
    cxx = _compiler()
    if cxx is None:
        log.warning("no C++ compiler found: GRaF's CPU inference uses its torch path (slower, same results)")
        return None
    try:
        lib = ctypes.CDLL(str(_build(cxx)))
    except (OSError, RuntimeError) as exc:
        log.warning("the attention kernel could not be built or loaded (%s): GRaF uses its torch path", exc)
        return None
    fn = lib.graf_attention
    fn.restype = None
    fn.argtypes = [ctypes.c_void_p] * 5 + [ctypes.c_int64] * 11
    lib.graf_attention_max_dim.restype = ctypes.c_int
    lib.graf_attention_max_keys.restype = ctypes.c_int
    lib.graf_block_limits.restype = ctypes.c_int
    lib.graf_block_limits.argtypes = [ctypes.c_int]
    blk = lib.graf_block
    blk.restype = None
    blk.argtypes = [ctypes.POINTER(BlockWeights), ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64]
    blk.argtypes += [ctypes.c_int64] * 3 + [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p]
    blk.argtypes += [ctypes.c_int64]
    mlp_fn = lib.graf_mlp
    mlp_fn.restype = None
    mlp_fn.argtypes = [ctypes.c_void_p] * 4 + [ctypes.c_int64] * 2 + [ctypes.c_void_p, ctypes.c_int64]
    mlp_fn.argtypes += [ctypes.c_void_p, ctypes.c_void_p] + [ctypes.c_int64] * 4
    rp = lib.graf_ray_pass
    rp.restype = None
    rp.argtypes = [ctypes.POINTER(RayPass), ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64]
    rp.argtypes += [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p] + [ctypes.c_int64] * 3
    lib.graf_ray_pass_lanes.restype = None
    lib.graf_ray_pass_lanes.argtypes = rp.argtypes
    lib.graf_attn_train_fwd.restype = None
    lib.graf_attn_train_fwd.argtypes = [ctypes.POINTER(AttnArgs), ctypes.c_void_p, ctypes.c_void_p]
    lib.graf_attn_train_fwd.argtypes += [ctypes.c_int64] * 2
    lib.graf_attn_train_bwd.restype = None
    lib.graf_attn_train_bwd.argtypes = [ctypes.POINTER(AttnArgs)] + [ctypes.c_void_p] * 6 + [ctypes.c_int64] * 2
    return lib


class BlockWeights(ctypes.Structure):
    """``struct BlockWeights`` of attention_cpu.cpp: one post-norm block's weights (pointers) and sizes."""

    _fields_ = [(n, ctypes.c_void_p) for n in ("wq", "bq", "wkv", "bkv", "wo", "bo", "g1", "be1")]
    _fields_ += [(n, ctypes.c_void_p) for n in ("w1", "b1", "w2", "b2", "g2", "be2")]
    _fields_ += [("eps1", ctypes.c_float), ("eps2", ctypes.c_float)]
    _fields_ += [(n, ctypes.c_int64) for n in ("d", "H", "Dh", "F")]


class AttnArgs(ctypes.Structure):
    """``struct AttnArgs`` of attention_cpu.cpp: the operands (pointers, element strides) of the training attention."""

    _fields_ = [(n, ctypes.c_void_p) for n in ("q", "k", "v", "mask")]
    _fields_ += [(n, ctypes.c_int64) for n in ("qg", "qs", "qh", "kg", "ks", "kh", "vg", "vs", "vh", "mask_stride")]
    _fields_ += [(n, ctypes.c_int64) for n in ("H", "Dh", "Sq", "Sk", "dqs", "dks")]
    _fields_ += [("scale", ctypes.c_float)]


class RayPass(ctypes.Structure):
    """``struct RayPass`` of attention_cpu.cpp: GRaF's scene blocks, MLP2 and ray blocks (pointers) and sizes."""

    _fields_ = [
        ("scene", ctypes.POINTER(ctypes.POINTER(BlockWeights))),
        ("ray", ctypes.POINTER(ctypes.POINTER(BlockWeights))),
    ]
    _fields_ += [(n, ctypes.c_void_p) for n in ("w1", "b1", "w2", "b2")]
    _fields_ += [(n, ctypes.c_int64) for n in ("n_scene", "n_ray", "d", "m")]


def library() -> ctypes.CDLL | None:
    """The loaded kernel library, or None where it cannot be had (built at most once per process)."""
    if "lib" not in _state:
        with _lock:
            if "lib" not in _state:
                _state["lib"] = _load()
    return _state["lib"]


def available() -> bool:
    return library() is not None


def _feature_major(x: torch.Tensor) -> bool:
    """``[B, D, N]`` float32 on the CPU, each entry's rows contiguous (strides ``(any, N, 1)``)."""
    return x.dtype == torch.float32 and x.device.type == "cpu" and x.stride(2) == 1 and x.stride(1) == x.shape[2]


def supports(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> bool:
    """Whether the kernel takes these operands (see :func:`attention`) on this machine."""
    lib = library()
    if lib is None or not all(_feature_major(t) for t in (q, k, v)):
        return False
    return max(q.shape[1], v.shape[1]) <= lib.graf_attention_max_dim() and k.shape[2] <= lib.graf_attention_max_keys()


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """``softmax(q^T k) v^T``, transposed: queries ``q [B, Dk, Sq]``, keys ``k [B, Dk, Sk]``, values ``v [B, Dv,
    Sk]`` (feature-major; the scale already in ``q``), optional key mask ``[B, Sk]`` (True = attend; at least one
    per entry) -> ``[B, Dv, Sq]``.  Single-threaded: callers parallelise over chunks of rays.  Only where
    :func:`supports` says so."""
    lib = library()
    B, Dk, Sq = q.shape
    Dv, Sk = v.shape[1], k.shape[2]
    out = torch.empty(B, Dv, Sq, dtype=torch.float32)
    if mask is not None:
        mask = mask.to(torch.uint8).expand(B, Sk).contiguous()
    lib.graf_attention(
        q.data_ptr(),
        k.data_ptr(),
        v.data_ptr(),
        None if mask is None else mask.data_ptr(),
        out.data_ptr(),
        0,
        B,
        Dk,
        Dv,
        Sq,
        Sk,
        q.stride(0),
        k.stride(0),
        v.stride(0),
        0 if mask is None else mask.stride(0),
        out.stride(0),
    )
    return out


def block_supported(d: int, inner: int, keys: int) -> bool:
    """Whether :func:`block` takes a block of width ``d``, inner widths (heads x head size, FFN) at most
    ``inner`` and ``keys`` keys per entry, on this machine."""
    lib = library()
    return (
        lib is not None
        and d <= lib.graf_block_limits(0)
        and inner <= lib.graf_block_limits(1)
        and keys <= lib.graf_attention_max_keys()
    )


def block(
    weights: BlockWeights,
    x: torch.Tensor,
    context: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """One fused post-norm block over feature-major entries ``x [n, d, S]`` (contiguous float32): self-attention,
    or cross-attention over ``context [n or 1, d, L]`` with an optional key mask ``[n or 1, keys]`` (True =
    attend).  Returns ``[n, d, S]``.  ``weights``: from :func:`graf.models.graf.kernels.blocks.block_weights`."""
    lib = library()
    n, _, S = x.shape
    y = torch.empty_like(x)
    if context is not None:
        context = context.contiguous()
    if mask is not None:
        mask = mask.to(torch.uint8).contiguous()
    lib.graf_block(
        ctypes.byref(weights),
        x.data_ptr(),
        x.stride(0),
        y.data_ptr(),
        y.stride(0),
        0,
        n,
        S,
        None if context is None else context.data_ptr(),
        0 if context is None or context.shape[0] == 1 else context.stride(0),
        0 if context is None else context.shape[2],
        None if mask is None else mask.data_ptr(),
        0 if mask is None or mask.shape[0] == 1 else mask.stride(0),
    )
    return y


def mlp_supported(d: int, hidden: int) -> bool:
    """Whether :func:`mlp` takes an MLP ``d -> hidden -> d`` on this machine."""
    lib = library()
    return lib is not None and d <= lib.graf_block_limits(0) and hidden <= lib.graf_block_limits(1)


def mlp(weights: tuple[torch.Tensor, ...], x: torch.Tensor, code: torch.Tensor | None = None) -> torch.Tensor:
    """``W2 relu(W1 x + b1) + b2 (+ code)`` over feature-major entries ``x [n, d, S]`` (contiguous float32), with
    ``code`` token-major ``[n, S, d]`` (contiguous) added: ``[n, d, S]``.  ``weights``: ``(W1 [m, d], b1 [m],
    W2 [d, m], b2 [d])``, contiguous float32; only where :func:`mlp_supported` says so."""
    lib = library()
    w1, b1, w2, b2 = weights
    n, d, S = x.shape
    y = torch.empty_like(x)
    if code is not None:
        code = code.contiguous()
    lib.graf_mlp(
        w1.data_ptr(),
        b1.data_ptr(),
        w2.data_ptr(),
        b2.data_ptr(),
        d,
        w1.shape[0],
        x.data_ptr(),
        x.stride(0),
        None if code is None else code.data_ptr(),
        y.data_ptr(),
        y.stride(0),
        0,
        n,
        S,
    )
    return y


def ray_pass_weights(scene: list[BlockWeights], ray: list[BlockWeights], mlp: tuple[torch.Tensor, ...]) -> RayPass:
    """The :func:`ray_pass` weights: the scene blocks', the ray blocks' (:class:`BlockWeights`, kept alive by the
    struct) and MLP2's ``(W1 [m, d], b1, W2 [d, m], b2)`` (contiguous float32)."""
    ptr = ctypes.POINTER(BlockWeights)
    scene_arr = (ptr * len(scene))(*[ctypes.pointer(w) for w in scene])
    ray_arr = (ptr * len(ray))(*[ctypes.pointer(w) for w in ray])
    w1, b1, w2, b2 = mlp
    p = RayPass(scene_arr, ray_arr, w1.data_ptr(), b1.data_ptr(), w2.data_ptr(), b2.data_ptr())
    p.n_scene, p.n_ray, p.d, p.m = len(scene), len(ray), w1.shape[1], w1.shape[0]
    p.keep = (scene, ray, mlp, scene_arr, ray_arr)
    return p


LANES = 16  # floats per vector in the kernels


def lane_fill(count: int) -> float:
    """The share of vector lanes in use when ``count`` items are packed 16 to a vector."""
    return count / (-(-count // LANES) * LANES)


def choose_layout(n: int, S: int) -> str:
    """:func:`ray_pass`'s layout for ``n`` rays of ``S`` voxels: ``rays`` for short rays whose positions leave
    many lanes idle (S <= 12, or S <= 24 filling under 70% of its vectors) when the rays fill more lanes than the
    positions, else ``positions``.  The rays layout loads a vector per key (each lane its own ray's) where the
    positions layout broadcasts one float, so at full vectors it is slower, and more so as S grows; the bounds
    are where the two crossed on the reference 2-core AMD EPYC (S = 3: rays 0.21x the time, 8: 0.55x, 17: 0.69x,
    24: 0.98x, 32: 1.47x, 64: 1.81x; one thread, GRaF's CPU sizes)."""
    short = S <= 12 or (S <= 24 and lane_fill(S) < 0.7)
    return "rays" if short and lane_fill(n) > lane_fill(S) else "positions"


def ray_pass(
    weights: RayPass,
    x: torch.Tensor,
    tokens: torch.Tensor,
    mask: torch.Tensor | None,
    code: torch.Tensor,
    layout: str = "auto",
) -> torch.Tensor:
    """GRaF's rays through the scene blocks, MLP2 (plus ``code``), the ray blocks and the mean over each ray:
    queries ``x [n, S, d]``, ``tokens [n or 1, L, d]``, key ``mask [n or 1, L]`` (True = attend) or None, distance
    ``code [n, S, d]`` (token-major) -> ``[n, d]``.  ``layout``: ``positions`` (16 positions of a ray per vector,
    ray by ray), ``rays`` (16 rays per vector, position by position; the same arithmetic, the same bits) or
    ``auto`` (:func:`choose_layout`).  Where
    :func:`block_supported` and :func:`mlp_supported` hold for every part."""
    lib = library()
    n, S, d = x.shape
    if layout == "auto":
        layout = choose_layout(n, S)
    fn = {"rays": lib.graf_ray_pass_lanes, "positions": lib.graf_ray_pass}[layout]
    x, tokens, code = x.contiguous(), tokens.contiguous(), code.contiguous()
    if mask is not None:
        mask = mask.to(torch.uint8).contiguous()
    out = torch.empty(n, d, dtype=torch.float32)
    fn(
        ctypes.byref(weights),
        x.data_ptr(),
        tokens.data_ptr(),
        0 if tokens.shape[0] == 1 else tokens.stride(0),
        tokens.shape[1],
        None if mask is None else mask.data_ptr(),
        0 if mask is None or mask.shape[0] == 1 else mask.stride(0),
        code.data_ptr(),
        out.data_ptr(),
        0,
        n,
        S,
    )
    return out
