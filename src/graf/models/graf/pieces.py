"""A training step's rays in pieces, each piece forward and backward on its own thread (GRaF on a CPU).

GRaF's operations are many and small (width 16): spread over torch's intra-op threads, each one pays a
synchronisation, and beside another busy process every operation waits for the slowest thread (training ran
15-20x slower beside one busy process).  Here the step is cut where it is cheap to cut:

1. the batch's context (:meth:`GRaFModule.prepare`: the neighbor encoder, the per-batch tables) once, on torch's
   threads (all of those set, whatever the load: a thread count can change a convolution's last bits);
2. the rays in ``pieces`` fixed slices (each target's rays cut alike), each rendered on a worker thread with one
   intra-op thread and its own autograd graph from *detached copies* of the context's tensors;
3. the loss on the whole prediction (any loss, per-target ones included), in this thread;
4. each piece's backward on a worker thread (``torch.autograd.grad`` to the parameters and the context copies);
   the pieces' gradients summed in piece order, then the context's backward through the encoder.

The pieces are fixed by the step, not by the threads, so a result does not depend on how many worker threads ran
them or in which order they finished: a busy machine gets fewer workers (:func:`graf.models.graf.inference.
serial_threads`), not other bits.  Within float rounding each parameter gets the gradient of the plain step
(tests/models/test_graf_fast_training.py).  Not under data-parallel training (DDP reduces the gradients that autograd
accumulates; a step there renders its rays in one piece, still through the kernel and the padded groups).
"""

from __future__ import annotations

import torch

from graf.models.graf.inference import serial_threads
from graf.models.graf.kernels.train import worker_pool


def _detach(value, pairs: list):
    """``value`` (a context: dicts, lists, tuples of tensors) with every tensor that needs a gradient replaced by a
    detached copy that requires one; ``pairs`` collects ``(original, copy)``."""
    if isinstance(value, torch.Tensor):
        if not value.requires_grad:
            return value
        leaf = value.detach().requires_grad_()
        pairs.append((value, leaf))
        return leaf
    if isinstance(value, dict):
        return {k: _detach(v, pairs) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_detach(v, pairs) for v in value)
    return value


def _map(fn, items: list, threads: int) -> list:
    """``[fn(item) for item in items]`` on up to ``threads`` worker threads, each with one intra-op thread; in order."""
    workers = min(len(items), max(1, serial_threads(threads)))
    if workers <= 1:
        before = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return [fn(item) for item in items]
        finally:
            torch.set_num_threads(before)
    before = torch.get_num_threads()
    torch.set_num_threads(1)

    def run(item):
        torch.set_num_threads(1)
        with torch.enable_grad():
            return fn(item)

    try:
        return list(worker_pool(workers).map(run, items))
    finally:
        torch.set_num_threads(before)


class PieceStep:
    """One training step's ray pass in ``pieces`` (see module doc).

    Args:
        render: ``render(ctx, pix [B, r]) -> [B, r]`` (the model's).
        ctx: the batch's context (:meth:`GRaFModule.prepare`, with its autograd graph).
        pix: the step's pixels ``[B, R]``.
        params: the parameters to differentiate (those that need a gradient).
        pieces: the number of slices of each target's rays (at most R).
        threads: worker threads at most (fewer while other processes are busy).
    """

    def __init__(self, render, ctx: dict, pix: torch.Tensor, params: list, pieces: int, threads: int):
        self.pairs: list = []
        self.ctx = _detach(ctx, self.pairs)
        self.params, self.threads = params, int(threads)
        self.slices = [s for s in torch.tensor_split(torch.arange(pix.shape[1]), max(1, int(pieces))) if len(s)]
        self.pix = pix
        self.render = render
        self.outputs: list = []

    def forward(self) -> torch.Tensor:
        """The prediction ``[B, R]``; its backward (whatever calls it: Lightning, a script's ``loss.backward()``)
        runs :meth:`backward`."""
        self.outputs = _map(lambda s: self.render(self.ctx, self.pix[:, s]), self.slices, self.threads)
        pred = torch.cat([o.detach() for o in self.outputs], dim=1)
        return _Pieces.apply(self.params[0], pred, self)

    def backward(self, grad: torch.Tensor) -> None:
        """Each piece's backward from ``grad [B, R]`` (the loss's gradient of the prediction), the gradients summed
        in piece order into the parameters' ``.grad`` and into the context, then the context's backward."""
        leaves = [leaf for _, leaf in self.pairs]
        inputs = self.params + leaves
        at = [0]
        for s in self.slices:
            at.append(at[-1] + len(s))

        def piece_grads(i):
            out = self.outputs[i]
            if not out.requires_grad:
                return [None] * len(inputs)
            return torch.autograd.grad(out, inputs, grad[:, at[i] : at[i + 1]], allow_unused=True)

        grads = _map(piece_grads, list(range(len(self.slices))), self.threads)
        totals = []
        for j in range(len(inputs)):
            parts = [g[j] for g in grads if g[j] is not None]
            total = None
            for part in parts:  # piece order: the same sum however the pieces were scheduled
                total = part if total is None else total + part
            totals.append(total)
        for p, g in zip(self.params, totals[: len(self.params)]):
            if g is not None:
                p.grad = g if p.grad is None else p.grad + g
        originals = [(orig, g) for (orig, _), g in zip(self.pairs, totals[len(self.params) :]) if g is not None]
        if originals:
            torch.autograd.backward([o for o, _ in originals], [g for _, g in originals])
        self.outputs, self.pairs = [], []


class _Pieces(torch.autograd.Function):
    """The prediction as an autograd node: its backward runs the pieces' (:meth:`PieceStep.backward`), which write
    the parameters' gradients themselves; ``anchor`` (a parameter) only ties the node into the loss's graph."""

    @staticmethod
    def forward(ctx, anchor, pred, step):
        ctx.step = step
        return pred.clone()

    @staticmethod
    def backward(ctx, grad):
        step, ctx.step = ctx.step, None
        step.backward(grad.contiguous())
        return None, None, None


def piece_prediction(model, batch: dict, pix: torch.Tensor) -> torch.Tensor | None:
    """A GRaF training step's prediction ``[B, R]`` through :class:`PieceStep`, or None where the pieces do not apply:
    not on a CPU, under autocast, without trainable parameters, or under data-parallel training (DDP reduces the
    gradients autograd accumulates; the pieces write theirs themselves).  The encoder runs on the threads set,
    whatever the load (a thread count can change its last bits); the pieces on as many workers as the load leaves."""
    params = [p for p in model.parameters() if p.requires_grad]
    distributed = torch.distributed.is_available() and torch.distributed.is_initialized()
    if not params or pix.device.type != "cpu" or distributed or torch.is_autocast_enabled("cpu"):
        return None
    ctx = model.prepare(batch)
    pieces = model.train_pieces or torch.get_num_threads()
    return PieceStep(model.render, ctx, pix, params, pieces, torch.get_num_threads()).forward()
