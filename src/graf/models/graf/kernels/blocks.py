"""GRaF's Transformer blocks at inference on a CPU, feature-major: the same function as the blocks' ``forward``
(:mod:`graf.models.graf.attention`), within float rounding, at a fraction of its cost.

GRaF's attention runs over many short sequences (a ray's S voxels, or its L neighbor tokens) with narrow heads
(10 of 8 in the ray transformer, 1 of 16 in the scene blocks).  The plain path splits the projections into
heads (copies), writes every score matrix to memory, runs softmax over rows of S and multiplies tiny
matrices, one call per (ray, head).  Here:

- the q, k and v projections are one batched matmul whose output is already *feature-major* per head,
  ``[rays, heads, (q | k | v), head_dim, S]`` (the weights are reordered, the ``1/sqrt(head_dim)`` scale folded
  into q's), so heads and rays merge into one batch axis without a copy;
- the attention itself is :func:`graf.models.graf.kernels.native.attention` (scores, softmax and the weighted
  sum fused, 16 queries per vector) where the compiled kernel is available, else the same arithmetic in torch
  (:func:`torch_attention`);
- the output projection reads the feature-major result directly.

Everything else (residuals, LayerNorms, FFNs) is the block's own modules.  Where the compiled library is there,
:func:`run_blocks` goes further: each whole block (projections, attention, residuals, LayerNorms, FFN) is one
call of :func:`graf.models.graf.kernels.native.block`, 16 positions per vector, nothing but the block's input
and output in memory.  Inference only: no autograd.
"""

from __future__ import annotations

import torch
from torch import nn

from graf.models.graf.cache import weights_stamp
from graf.models.graf.kernels import native

LOG2_E = 1.4426950408889634


def torch_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """:func:`native.attention`'s arithmetic in torch operations (where the kernel is not available)."""
    a = torch.bmm(q.transpose(1, 2), k)  # [B, Sq, Sk]
    if mask is not None:
        a = a.masked_fill(~mask.bool()[:, None, :], float("-inf"))
    return torch.bmm(v, a.softmax(dim=-1).transpose(1, 2))


def attention_fm(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Feature-major attention ``[B, Dk, Sq]``, ``[B, Dk, Sk]``, ``[B, Dv, Sk]`` -> ``[B, Dv, Sq]``: the kernel
    where it takes the operands, else torch."""
    if native.supports(q, k, v):
        return native.attention(q, k, v, mask)
    return torch_attention(q, k, v, mask)


def _project(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Token-major ``x [B, N, d]`` -> ``(x W^T + b)^T [B, R, N]`` (feature-major) with one batched matmul."""
    return _project_fm(x.transpose(1, 2), weight, bias)


def _head_major(attn: nn.Module, parts: tuple[str, ...], scale_q: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """The projections ``parts`` (of ``q``, ``k``, ``v``) stacked per head: rows ``(head, part, head_dim)``."""
    H, Dh = attn.num_heads, attn.head_dim
    d = attn.q.in_features
    s = Dh**-0.5
    ws = [getattr(attn, p).weight * (s if p == "q" and scale_q else 1.0) for p in parts]
    bs = [getattr(attn, p).bias * (s if p == "q" and scale_q else 1.0) for p in parts]
    w = torch.stack([w.view(H, Dh, d) for w in ws], dim=1).reshape(H * len(parts) * Dh, d)
    b = torch.stack([b.view(H, Dh) for b in bs], dim=1).reshape(-1)
    return w, b


def _output(attn: nn.Module, o: torch.Tensor, B: int, N: int) -> torch.Tensor:
    """Heads' outputs ``[B * H, Dh, N]`` -> the output projection, token-major ``[B, N, d]``."""
    o = o.view(B, attn.num_heads * attn.head_dim, N)
    return _project_fm(o, attn.out.weight, attn.out.bias).transpose(1, 2)


def _project_fm(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Feature-major ``x [B, C, N]`` -> ``W x + b [B, R, N]``."""
    B, C, N = x.shape
    R = weight.shape[0]
    return torch.baddbmm(bias[None, :, None].expand(B, R, N), weight.expand(B, R, C), x)


def self_attention(attn: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``attn(x, x)`` without a key mask: ``x [B, N, d]`` -> ``[B, N, d]``."""
    B, N, _ = x.shape
    H, Dh = attn.num_heads, attn.head_dim
    w, b = _head_major(attn, ("q", "k", "v"), scale_q=True)
    qkv = _project(x, w, b).view(B * H, 3 * Dh, N)
    o = attention_fm(qkv[:, :Dh], qkv[:, Dh : 2 * Dh], qkv[:, 2 * Dh :], None)
    return _output(attn, o, B, N)


def cross_attention(
    attn: nn.Module, x: torch.Tensor, context: torch.Tensor, key_mask: torch.Tensor | None
) -> torch.Tensor:
    """``attn(x, context, key_mask)``: queries ``x [B, Nq, d]``, context ``[B, Nk, d]`` -> ``[B, Nq, d]``."""
    B, Nq, _ = x.shape
    Nk = context.shape[1]
    H, Dh = attn.num_heads, attn.head_dim
    wq, bq = _head_major(attn, ("q",), scale_q=True)
    wkv, bkv = _head_major(attn, ("k", "v"), scale_q=False)
    q = _project(x, wq, bq).view(B * H, Dh, Nq)
    kv = _project(context, wkv, bkv).view(context.shape[0] * H, 2 * Dh, Nk)
    if context.shape[0] != B:  # one context for every entry
        kv = kv.repeat(B, 1, 1)
    mask = None if key_mask is None else key_mask.bool().expand(B, -1).repeat_interleave(H, dim=0)
    o = attention_fm(q, kv[:, :Dh], kv[:, Dh:], mask)
    return _output(attn, o, B, Nq)


def block_forward(
    blk: nn.Module, x: torch.Tensor, context: torch.Tensor | None = None, key_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """A post-norm block (:class:`graf.models.graf.attention.CrossAttentionBlock` with ``context``, else
    :class:`~graf.models.graf.attention.SelfAttentionBlock`) at inference, feature-major."""
    a = self_attention(blk.attn, x) if context is None else cross_attention(blk.attn, x, context, key_mask)
    x = blk.norm1(x + a)
    return blk.norm2(x + blk.ffn(x))


def block_weights(blk: nn.Module) -> native.BlockWeights:
    """The fused kernel's weights of a post-norm block (cached on the block while its weights are unchanged)."""
    stamp = weights_stamp(blk)
    cached = getattr(blk, "_fused_weights", None)
    if cached is not None and cached[0] == stamp:
        return cached[1]
    attn = blk.attn
    wq, bq = (t * LOG2_E for t in _head_major(attn, ("q",), scale_q=True))  # the kernel's scores are in base 2
    wkv, bkv = _head_major(attn, ("k", "v"), scale_q=False)
    lin1, lin2 = blk.ffn[0], blk.ffn[2]
    keep = [t.detach().float().contiguous() for t in (wq, bq, wkv, bkv, attn.out.weight, attn.out.bias)]
    keep += [t.detach().float().contiguous() for t in (blk.norm1.weight, blk.norm1.bias, lin1.weight, lin1.bias)]
    keep += [t.detach().float().contiguous() for t in (lin2.weight, lin2.bias, blk.norm2.weight, blk.norm2.bias)]
    w = native.BlockWeights(*[t.data_ptr() for t in keep], blk.norm1.eps, blk.norm2.eps)
    w.d, w.H, w.Dh, w.F = attn.q.in_features, attn.num_heads, attn.head_dim, lin1.out_features
    w.keep = keep  # the tensors the pointers point into live as long as the struct
    blk._fused_weights = (stamp, w)
    return w


def fusable(blocks: nn.ModuleList, keys: int) -> bool:
    return all(
        isinstance(b.ffn[1], nn.ReLU)
        and native.block_supported(
            b.attn.q.in_features, max(b.attn.num_heads * b.attn.head_dim, b.ffn[0].out_features), keys
        )
        for b in blocks
    )


def mlp_weights(seq: nn.Sequential) -> tuple[torch.Tensor, ...]:
    """``(W1, b1, W2, b2)`` of an MLP ``Linear, ReLU, Linear`` for :func:`native.mlp` (cached on it while its
    weights are unchanged)."""
    stamp = weights_stamp(seq)
    cached = getattr(seq, "_fused_weights", None)
    if cached is None or cached[0] != stamp:
        keep = tuple(t.detach().float().contiguous() for t in (seq[0].weight, seq[0].bias, seq[2].weight, seq[2].bias))
        cached = seq._fused_weights = (stamp, keep)
    return cached[1]


def mlp_fusable(seq: nn.Module) -> bool:
    """Whether :func:`native.mlp` runs ``seq`` (``Linear(d, m), ReLU, Linear(m, d)``) on this machine."""
    return (
        isinstance(seq, nn.Sequential)
        and len(seq) == 3
        and isinstance(seq[1], nn.ReLU)
        and seq[0].in_features == seq[2].out_features
        and native.mlp_supported(seq[0].in_features, seq[0].out_features)
    )


def run_blocks(
    blocks: nn.ModuleList, x: torch.Tensor, context: torch.Tensor | None = None, key_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """``blocks`` one after the other over token-major ``x [B, N, d]`` (cross-attention over ``context [B or 1,
    L, d]`` with ``key_mask [B or 1, L]`` when given): each a fused kernel call where the library is there and
    takes the sizes, else :func:`block_forward`.  Returns ``[B, N, d]``."""
    keys = x.shape[1] if context is None else context.shape[1]
    if not fusable(blocks, keys):
        for blk in blocks:
            x = block_forward(blk, x, context, key_mask)
        return x
    cf = None if context is None else context.transpose(1, 2).contiguous()
    return fused_blocks(blocks, x.transpose(1, 2).contiguous(), cf, key_mask).transpose(1, 2)


def fused_blocks(
    blocks: nn.ModuleList, xf: torch.Tensor, cf: torch.Tensor | None = None, key_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """:func:`run_blocks` feature-major, fused only (where :func:`fusable`): ``xf [B, d, N]``, ``cf [B or 1, d,
    L]`` (contiguous) -> ``[B, d, N]``."""
    for blk in blocks:
        xf = native.block(block_weights(blk), xf, cf, key_mask)
    return xf


def ray_pass_weights(model: nn.Module) -> native.RayPass:
    """:func:`native.ray_pass`'s weights of a GRaF model (its ``scene_blocks``, ``mlp2`` and ``ray_blocks``; cached
    on the model while their weights are unchanged)."""
    stamp = weights_stamp(model.scene_blocks, model.mlp2, model.ray_blocks)
    cached = getattr(model, "_fused_ray_pass", None)
    if cached is None or cached[0] != stamp:
        scene = [block_weights(b) for b in model.scene_blocks]
        ray = [block_weights(b) for b in model.ray_blocks]
        cached = (stamp, native.ray_pass_weights(scene, ray, mlp_weights(model.mlp2)))
        model._fused_ray_pass = cached
    return cached[1]
