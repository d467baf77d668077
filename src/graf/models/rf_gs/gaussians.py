"""The Gaussians of RF Gaussian splatting and the deformation MLP that moves them with the transmitter.

:class:`GaussianField` holds N Gaussians on the spectrum grid, one row each (``nn.Parameter``):

* ``elevation [N]``, ``azimuth [N]``: the base mean (deg; azimuth taken modulo 360 by the rasterizer);
* ``log_sigma [N, 2]``: the log of the base widths (deg) in elevation and azimuth;
* ``amplitude [N]``: the base amplitude (signed).

and the deformation MLP (SwiftWRF's idea): the transmitter position ``p`` in the scene's normalised frame
(:func:`graf.geometry.encoding.normalize_positions`: centred on the scene box of the batch's ``bounds`` and divided
by its largest half-extent, so the frame comes from the scene, not from constants), encoded
(:class:`~graf.geometry.encoding.PositionalEncoding`, ``pe_freqs`` frequencies ``2^k pi`` and the raw input),
through ``depth`` ReLU layers of ``width``, then a head of five offsets per Gaussian ``o [B, N, 5]``.  The head is
stored per Gaussian (``head_weight [N, 5, width]``, ``head_bias [N, 5]``) so that pruning, splitting and
loading a checkpoint of another Gaussian count gather rows of every per-Gaussian tensor alike.

The deformed Gaussian k for transmitter b (:meth:`GaussianField.forward`):

* ``elevation = clamp(e_k + max_shift tanh(o_0), 0.5, 90.5)`` (the grid's edges: a mean never leaves the grid);
* ``azimuth = a_k + max_shift tanh(o_1)``;
* ``sigma_el, sigma_az = clamp(exp(log_sigma_k + o_{2,3}), sigma_min, sigma_max)``;
* ``amplitude = w_k + o_4``.

A fresh field is drawn from torch's generator: means uniform on the grid, widths ``init_sigma``, amplitudes
``init_amplitude``; the head's weights normal with standard deviation ``head_init`` and its biases zero, so every
transmitter starts near the base Gaussians.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from graf.errors import ConfigError
from graf.geometry.encoding import PositionalEncoding
from graf.geometry.grid import N_AZIMUTH, N_ELEVATION
from graf.models.rf_gs.rasterizer import ELEVATION_EDGES

OFFSETS = 5  # per Gaussian: elevation, azimuth, log width (elevation, azimuth), amplitude
PER_GAUSSIAN = ("elevation", "azimuth", "log_sigma", "amplitude", "head_weight", "head_bias")
VALUE_BYTES = 4  # float32, every per-Gaussian parameter and what rendering makes of it
TRAINING_COPIES = 4  # a parameter row in training: the weights, their gradients and Adam's two moments
# values per Gaussian per spectrum rendered at once: its elevation and azimuth profiles, offsets, deformed values
RENDER_VALUES = N_ELEVATION + N_AZIMUTH + 2 * OFFSETS


def row_shapes(width: int) -> dict[str, tuple[int, ...]]:
    """The shape of one Gaussian's row of each per-Gaussian parameter (:data:`PER_GAUSSIAN`) at this head width."""
    return {
        "elevation": (),
        "azimuth": (),
        "log_sigma": (2,),
        "amplitude": (),
        "head_weight": (OFFSETS, int(width)),
        "head_bias": (OFFSETS,),
    }


def gaussian_bytes(width: int, spectra: int) -> int:
    """The memory one Gaussian takes, at the least, in a model rendering ``spectra`` spectra at once: its rows of
    the parameters (:func:`row_shapes`) :data:`TRAINING_COPIES` times over, and its :data:`RENDER_VALUES` per
    spectrum (what autograd keeps besides is not counted)."""
    row = sum(math.prod(shape) for shape in row_shapes(width).values())
    return VALUE_BYTES * (TRAINING_COPIES * row + int(spectra) * RENDER_VALUES)


def check_gaussian_memory(key: str, count: int, width: int, spectra: int, available: int, where: str) -> None:
    """Refuse, in one line naming the setting ``key``, a Gaussian count whose memory (:func:`gaussian_bytes`) is
    more than the ``available`` bytes of ``where`` (the machine's memory, a GPU's), before anything is allocated."""
    need = int(count) * gaussian_bytes(width, spectra)
    if need > available:
        raise ConfigError(
            f"model.{key}={count}: needs at least {need / 1e9:.1f} GB ({count:,} Gaussians x "
            f"{gaussian_bytes(width, spectra):,} bytes: their parameters at model.width={width}, with gradients and "
            f"Adam's moments, and {spectra} spectra rendered at once, model.chunk_spectra), more than the "
            f"{available / 1e9:.1f} GB {where} has free; lower it"
        )


class GaussianField(nn.Module):
    """``forward(tx_norm [B, 3]) -> {"elevation", "azimuth", "sigma_el", "sigma_az", "amplitude"}`` (each
    ``[B, N]``): N base Gaussians deformed per transmitter (see the module docstring).  The Gaussian count follows
    a loaded state dict (:meth:`resize`, run by a load pre-hook)."""

    def __init__(
        self,
        num_gaussians: int,
        depth: int,
        width: int,
        pe_freqs: int,
        init_sigma: float,
        init_amplitude: float,
        sigma_min: float,
        sigma_max: float,
        max_shift: float,
        head_init: float,
    ):
        super().__init__()
        self.width, self.head_init = int(width), float(head_init)
        self.init_sigma, self.init_amplitude = float(init_sigma), float(init_amplitude)
        self.sigma_min, self.sigma_max, self.max_shift = float(sigma_min), float(sigma_max), float(max_shift)
        self.pe = PositionalEncoding(pe_freqs, include_input=True)
        dims = [self.pe.out_dim(3)] + [self.width] * int(depth)
        self.trunk = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        for name in PER_GAUSSIAN:
            self.register_parameter(name, nn.Parameter(torch.empty(0)))
        self.reset(int(num_gaussians))
        self.register_load_state_dict_pre_hook(_follow_loaded_count)

    @property
    def count(self) -> int:
        return int(self.amplitude.shape[0])

    def per_gaussian(self) -> list[nn.Parameter]:
        """The parameters with one row per Gaussian (what pruning, splitting and resizing gather)."""
        return [getattr(self, name) for name in PER_GAUSSIAN]

    def reset(self, n: int) -> None:
        """Draw n fresh Gaussians and head rows (see the module docstring)."""
        n = int(n)
        lo, hi = ELEVATION_EDGES
        rows = {name: (n, *shape) for name, shape in row_shapes(self.width).items()}
        fresh = {
            "elevation": lo + (hi - lo) * torch.rand(rows["elevation"]),
            "azimuth": 360.0 * torch.rand(rows["azimuth"]),
            "log_sigma": torch.full(rows["log_sigma"], math.log(self.init_sigma)),
            "amplitude": torch.full(rows["amplitude"], self.init_amplitude),
            "head_weight": torch.randn(rows["head_weight"]) * self.head_init,
            "head_bias": torch.zeros(rows["head_bias"]),
        }
        device = next(self.trunk.parameters()).device
        self._replace({name: value.to(device) for name, value in fresh.items()})

    def resize(self, n: int) -> dict:
        """Give every per-Gaussian parameter n rows (values to be overwritten: a checkpoint is loading)."""
        return self._replace({name: p.detach().new_zeros((int(n), *p.shape[1:])) for name, p in self._rows()})

    def select(self, index: torch.Tensor) -> dict:
        """Keep the rows ``index`` of every per-Gaussian parameter, in that order (repeats allowed: a split).
        Returns ``{old parameter: new parameter}`` (an optimiser holding the old ones must follow)."""
        return self._replace({name: p.detach()[index] for name, p in self._rows()})

    def _rows(self) -> list[tuple[str, nn.Parameter]]:
        return [(name, getattr(self, name)) for name in PER_GAUSSIAN]

    def _replace(self, values: dict[str, torch.Tensor]) -> dict:
        """New ``nn.Parameter`` objects for a new count (autograd keeps a leaf's shape: resizing ``.data`` in
        place would break the next backward); ``{old: new}``."""
        moved = {}
        for name, value in values.items():
            old = getattr(self, name)
            new = nn.Parameter(value.contiguous(), requires_grad=old.requires_grad)
            setattr(self, name, new)
            moved[old] = new
        return moved

    def offsets(self, tx_norm: torch.Tensor) -> torch.Tensor:
        """``[B, N, 5]``: the deformation MLP's offsets for transmitters at ``tx_norm [B, 3]`` (normalised)."""
        h = self.pe(tx_norm.float())
        for layer in self.trunk:
            h = torch.relu(layer(h))
        n = self.count
        out = torch.matmul(h, self.head_weight.reshape(n * OFFSETS, self.width).t().to(h.dtype))
        return out.reshape(-1, n, OFFSETS).float() + self.head_bias

    def forward(self, tx_norm: torch.Tensor) -> dict[str, torch.Tensor]:
        o = self.offsets(tx_norm)
        lo, hi = ELEVATION_EDGES
        shift = self.max_shift * torch.tanh(o[..., :2])
        sigma = torch.exp(self.log_sigma + o[..., 2:4]).clamp(self.sigma_min, self.sigma_max)
        return {
            "elevation": (self.elevation + shift[..., 0]).clamp(lo, hi),
            "azimuth": self.azimuth + shift[..., 1],
            "sigma_el": sigma[..., 0],
            "sigma_az": sigma[..., 1],
            "amplitude": self.amplitude + o[..., 4],
        }


def _follow_loaded_count(module: GaussianField, state_dict: dict, prefix: str, *args) -> None:
    """Load pre-hook: a state dict whose Gaussian count differs from the field's (a checkpoint written after
    densification) resizes the field first, so that it loads and then predicts as the checkpoint's model did."""
    stored = state_dict.get(prefix + "amplitude")
    if stored is not None and int(stored.shape[0]) != module.count:
        module.resize(int(stored.shape[0]))


def split_plan(score: torch.Tensor, magnitude: torch.Tensor, fraction: float, floor: float, cap: int):
    """``(keep, split)``: the Gaussians kept (``|amplitude|`` averaged over the steps since the last plan at least
    ``floor``; the strongest one kept if none is) and, among them, those to split: the ``fraction`` of the count
    with the largest ``score`` (the mean gradient norm of their means), fewer if the count would pass ``cap``."""
    keep = torch.nonzero(magnitude >= floor).flatten()
    if keep.numel() == 0:
        keep = magnitude.argmax().reshape(1)
    room = max(0, int(cap) - int(keep.numel()))
    want = min(room, math.ceil(float(fraction) * int(score.numel())), int(keep.numel()))
    order = torch.argsort(score[keep], descending=True)[:want]
    split = keep[order[score[keep][order] > 0]]
    return keep, split


def split_rows(field: GaussianField, keep: torch.Tensor, split: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """Apply a :func:`split_plan` to ``field``: the kept Gaussians that are not split, then two children per split
    one, placed at ``mean -/+ sigma / 2`` along the parent's wider base axis with that width times ``sqrt(3) / 2``
    and the amplitude (base and offset head) divided by ``sqrt(3)``: the pair keeps the parent's mean, variance and
    integral.  Returns the row index applied (each child takes its parent's row: what the optimiser's state
    follows) and ``{old parameter: new parameter}``."""
    single = keep[~torch.isin(keep, split)]
    index = torch.cat([single, split, split])
    moved = field.select(index)
    s = int(split.numel())
    if s == 0:
        return index, moved
    children = torch.arange(single.numel(), index.numel(), device=index.device)
    with torch.no_grad():
        axis = field.log_sigma[children].argmax(dim=1)  # 0: elevation, 1: azimuth
        half = 0.5 * torch.exp(field.log_sigma[children].gather(1, axis[:, None]).squeeze(1))
        sign = torch.cat([-torch.ones(s), torch.ones(s)]).to(half)
        for dim, mean in enumerate((field.elevation, field.azimuth)):
            mean[children] += torch.where(axis == dim, sign * half, torch.zeros_like(half))
        field.log_sigma[children, axis] += math.log(math.sqrt(3.0) / 2.0)
        root3 = math.sqrt(3.0)
        field.amplitude[children] /= root3
        field.head_weight[children, OFFSETS - 1] /= root3
        field.head_bias[children, OFFSETS - 1] /= root3
    return index, moved
