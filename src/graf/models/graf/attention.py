"""Post-norm Transformer blocks (supplement D) on ``F.scaled_dot_product_attention``.

One block: ``x = LayerNorm(x + Attention(x, context))``, then ``x = LayerNorm(x + FFN(x))`` with
``FFN = Linear(d, ffn_dim) -> ReLU -> Linear(ffn_dim, d)``.  Attention has ``num_heads`` heads of
``head_dim`` each (inner width ``num_heads * head_dim``, projected back to ``d``) and the usual
``1 / sqrt(head_dim)`` scaling.

* :class:`CrossAttentionBlock`: queries ``x [B, Nq, d]`` attend to ``context [B, Nk, d]`` (GRaF's scene
  representation: voxel queries over the neighbor tokens; 1 head of width d = 16).
* :class:`SelfAttentionBlock`: ``x [B, N, d]`` attends to itself (GRaF's ray transformer: 10 heads of
  8 on width-16 voxel tokens).

``key_mask [B, Nk]`` is True for real keys (padded keys get no attention weight); every row needs at
least one real key.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from graf.models.graf.kernels import train as train_kernel

KERNELS = ("auto", "sdpa", "math")
MATH_SCORES_PER_PIECE = 1 << 18  # the math kernel's score tensor per piece (1 MB in fp32: stays in cache)


def math_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """``softmax(q k^T / sqrt(Dh)) v`` with explicit matmuls, in pieces along the batch axis small enough
    for the score tensor to stay in cache.  On CPU this beats SDPA's fused kernel when the heads are narrow
    (GRaF's ray transformer: 10 heads of 8; measured by ``graf-bench`` and scripts/attention_kernels.py)."""
    B, H, Nq, Dh = q.shape
    Nk = k.shape[-2]
    scale = Dh**-0.5
    per = max(1, MATH_SCORES_PER_PIECE // max(1, H * Nq * Nk))
    # torch.split, not slicing: a slice's backward fills a zero tensor of the whole input per piece
    masks = [None] * -(-B // per) if mask is None else mask.expand(B, *mask.shape[1:]).split(per)
    out = []
    for qs, ks, vs, ms in zip(q.split(per), k.split(per), v.split(per), masks):
        a = torch.matmul(qs * scale, ks.transpose(-1, -2))
        if ms is not None:
            a = a.masked_fill(~ms, float("-inf"))
        out.append(torch.matmul(a.softmax(dim=-1), vs))
    return out[0] if len(out) == 1 else torch.cat(out)


class MultiHeadAttention(nn.Module):
    """Multi-head attention ``[..., Nq, d] x [..., Nk, d] -> [..., Nq, d]`` with a key mask, by ``kernel``: ``sdpa``
    (torch's fused attention) or ``math`` (explicit matmuls); with ``fused_training`` set by
    :class:`GRaFModule`, training on a CPU goes through the compiled kernel with its backward
    (:mod:`graf.models.graf.kernels.train`).  ``head_dim`` defaults to ``d_model // num_heads``."""

    def __init__(
        self, d_model: int, num_heads: int = 1, head_dim: int | None = None, dropout: float = 0.0, kernel: str = "sdpa"
    ):
        super().__init__()
        if kernel not in KERNELS:
            raise ValueError(f"attention kernel must be one of {KERNELS}, got {kernel!r}")
        self.kernel = kernel
        self.num_heads = int(num_heads)
        self.head_dim = int(head_dim) if head_dim is not None else d_model // self.num_heads
        inner = self.num_heads * self.head_dim
        self.q = nn.Linear(d_model, inner)
        self.k = nn.Linear(d_model, inner)
        self.v = nn.Linear(d_model, inner)
        self.out = nn.Linear(inner, d_model)
        self.dropout = float(dropout)
        self.fused_training = False  # with autograd on a CPU: the compiled kernel with its backward (set by the model)

    def _split(self, x: torch.Tensor) -> torch.Tensor:  # [B, N, H*Dh] -> [B, H, N, Dh]
        return x.unflatten(-1, (self.num_heads, self.head_dim)).transpose(1, 2)

    def _use_math(self, q: torch.Tensor) -> bool:
        if self.kernel == "math":
            return not (self.dropout and self.training)
        # auto: explicit matmuls on CPU for many short sequences of narrow heads, where SDPA's fused kernel
        # is slow (per-sequence overhead); SDPA everywhere else (GPUs, long query axes, dropout)
        return (
            self.kernel == "auto"
            and q.device.type == "cpu"
            and q.shape[-1] <= 16
            and q.shape[-2] <= 256
            and q.shape[0] > 1
            and not (self.dropout and self.training)
        )

    def _fused(self, x: torch.Tensor, context: torch.Tensor, key_mask: torch.Tensor | None) -> torch.Tensor | None:
        """The attention through :mod:`graf.models.graf.kernels.train` (token-major, no transposes; q, k and v
        of a self-attention in one projection, k and v of a cross-attention in one), or None where it does not
        apply (then the torch path runs: the same function within float rounding)."""
        H, Dh = self.num_heads, self.head_dim
        if x.dim() != 3 or context.dim() != 3 or x.shape[0] != context.shape[0] or (self.dropout and self.training):
            return None
        if context is x:
            w = torch.cat([self.q.weight, self.k.weight, self.v.weight])
            q, kv = F.linear(x, w, torch.cat([self.q.bias, self.k.bias, self.v.bias])), None
        else:
            w, b = torch.cat([self.k.weight, self.v.weight]), torch.cat([self.k.bias, self.v.bias])
            q, kv = self.q(x), F.linear(context, w, b)
        if not train_kernel.supported(q, kv, H, Dh, key_mask):
            return None
        y = train_kernel.attention(q, kv, H, Dh, key_mask, Dh**-0.5)  # [B, Nq, H, Dh]
        return self.out(y.flatten(-2))

    def forward(self, x: torch.Tensor, context: torch.Tensor, key_mask: torch.Tensor | None = None) -> torch.Tensor:
        if self.fused_training and torch.is_grad_enabled() and x.device.type == "cpu" and x.dtype == torch.float32:
            y = self._fused(x, context, key_mask)
            if y is not None:
                return y
        q, k, v = self._split(self.q(x)), self._split(self.k(context)), self._split(self.v(context))
        # [B, 1, 1, Nk], True = attend.  Callers pass None when nothing is padded (keeps SDPA's fused kernels)
        mask = None if key_mask is None else key_mask[:, None, None, :].to(torch.bool)
        # under autocast the projections may come out in different dtypes (a bf16 Linear vs fp32 input)
        dtype = torch.promote_types(torch.promote_types(q.dtype, k.dtype), v.dtype)
        q, k, v = q.to(dtype), k.to(dtype), v.to(dtype)
        if self._use_math(q):
            y = math_attention(q, k, v, mask)
        else:
            y = F.scaled_dot_product_attention(
                q, k, v, attn_mask=mask, dropout_p=self.dropout if self.training else 0.0
            )
        return self.out(y.transpose(1, 2).flatten(-2))


class _PostNormBlock(nn.Module):
    def __init__(
        self,
        d_model: int,
        num_heads: int,
        head_dim: int | None,
        ffn_dim: int,
        dropout: float = 0.0,
        kernel: str = "sdpa",
    ):
        super().__init__()
        self.attn = MultiHeadAttention(d_model, num_heads, head_dim, dropout, kernel)
        self.norm1 = nn.LayerNorm(d_model)
        self.ffn = nn.Sequential(nn.Linear(d_model, ffn_dim), nn.ReLU(), nn.Linear(ffn_dim, d_model))
        self.norm2 = nn.LayerNorm(d_model)

    def _block(self, x, context, key_mask):
        x = self.norm1(x + self.attn(x, context, key_mask))
        return self.norm2(x + self.ffn(x))


class CrossAttentionBlock(_PostNormBlock):
    """Queries attend to a context (default: one head of width ``d_model``)."""

    def __init__(
        self,
        d_model: int = 16,
        num_heads: int = 1,
        head_dim: int | None = None,
        ffn_dim: int = 64,
        dropout: float = 0.0,
        kernel: str = "sdpa",
    ):
        super().__init__(d_model, num_heads, head_dim, ffn_dim, dropout, kernel)

    def forward(self, x: torch.Tensor, context: torch.Tensor, key_mask: torch.Tensor | None = None) -> torch.Tensor:
        return self._block(x, context, key_mask)


class SelfAttentionBlock(_PostNormBlock):
    """Tokens attend to each other (default: 10 heads of 8 on width 16)."""

    def __init__(
        self,
        d_model: int = 16,
        num_heads: int = 10,
        head_dim: int | None = 8,
        ffn_dim: int = 64,
        dropout: float = 0.0,
        kernel: str = "sdpa",
    ):
        super().__init__(d_model, num_heads, head_dim, ffn_dim, dropout, kernel)

    def forward(self, x: torch.Tensor, key_mask: torch.Tensor | None = None) -> torch.Tensor:
        return self._block(x, x, key_mask)
