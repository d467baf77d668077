"""Neighbor selection shared by every method.

For a target transmitter position, the L nearest *known* transmitters by Euclidean distance, drawn from
the training split of the scene being evaluated, never the target itself (matched by id, so a distinct
transmitter at the same position is a valid neighbor at distance 0).  Optionally only candidates
within ``radius`` are used; when fewer than L lie inside, the radius is widened to the L-th nearest
candidate (and reported).  ``exclude_within`` removes every candidate closer than that distance to the
target, to emulate sparse measurements.  Ties are broken by candidate order, so results are
deterministic.

:func:`select_neighbors` is the pure function; :class:`NeighborSelector` is the configured object
(``conf/neighbors``) that converts lengths given in wavelengths and draws L at training time.

**Where the settings are decided.**  The presets in ``conf/neighbors`` are the one source of the values:
``random_3_10.yaml`` states the paper's protocol (L = 10, L_train = [3, 10], radius 10 wavelengths, nothing
excluded) and the other presets extend it, stating only what they change (``fixed``: L_train = [L, L];
``sparse``: exclude_within 0.25).  :class:`NeighborSelector` has no defaults of its own for L, L_train and
radius, so code that builds one names them; ``exclude_within`` defaults to 0 there, the plain nearest-neighbor
rule (nothing excluded), as in :func:`select_neighbors`.
"""

from __future__ import annotations

import logging
import numbers
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from graf.config_home import defaults_from
from graf.errors import ConfigError, UserError

log = logging.getLogger(__name__)


@dataclass
class Neighbors:
    """Result of a selection for T targets, padded to the largest L in the batch.

    index:    long ``[T, Lmax]`` row indices into the candidate array (0 where ``mask`` is False)
    mask:     bool ``[T, Lmax]`` True for real neighbors; each row's True entries come first
    distance: float ``[T, Lmax]`` distance to the target (0 where ``mask`` is False)
    widened:  bool ``[T]`` the radius held fewer than the requested L and was widened
    short:    bool ``[T]`` fewer than the requested L candidates exist at all
    """

    index: torch.Tensor
    mask: torch.Tensor
    distance: torch.Tensor
    widened: torch.Tensor
    short: torch.Tensor

    @property
    def counts(self) -> torch.Tensor:
        return self.mask.sum(dim=1)


class NoNeighborsError(UserError):
    """No candidate is left for a target (after excluding itself and those within ``exclude_within``)."""


def _per_target_counts(target_pos: torch.Tensor, cand_pos: torch.Tensor, L: int | torch.Tensor) -> torch.Tensor:
    """The checked inputs' neighbor count of each target: long ``[T]`` (each >= 1)."""
    if target_pos.ndim != 2 or target_pos.shape[-1] != 3:
        raise ValueError(f"target_pos must be [T, 3], got {tuple(target_pos.shape)}")
    if cand_pos.ndim != 2 or cand_pos.shape[-1] != 3:
        raise ValueError(f"cand_pos must be [M, 3], got {tuple(cand_pos.shape)}")
    if not (torch.isfinite(target_pos).all() and torch.isfinite(cand_pos).all()):
        raise ValueError("positions must be finite")
    T, device = target_pos.shape[0], target_pos.device
    Ls = (
        torch.as_tensor(L, dtype=torch.long, device=device).expand(T)
        if not torch.is_tensor(L) or L.ndim == 0
        else L.to(device=device, dtype=torch.long)
    )
    if Ls.shape != (T,):
        raise ValueError(f"L must be an int or a [T] tensor, got shape {tuple(Ls.shape)} for T={T}")
    if T and int(Ls.min()) < 1:
        raise ValueError(f"L must be >= 1, got {int(Ls.min())}")
    return Ls


def select_neighbors(
    target_pos: torch.Tensor,
    cand_pos: torch.Tensor,
    L: int | torch.Tensor,
    *,
    target_ids: torch.Tensor | None = None,
    cand_ids: torch.Tensor | None = None,
    radius: float | None = None,
    exclude_within: float = 0.0,
) -> Neighbors:
    """Select the L nearest candidates of each target.

    Args:
        target_pos: ``[T, 3]`` target positions.
        cand_pos: ``[M, 3]`` candidate (known, training) positions.
        L: neighbors per target, an int or a long tensor ``[T]`` (each >= 1).
        target_ids / cand_ids: ``[T]`` / ``[M]`` ids; a candidate with the target's id is never returned.
        radius: keep candidates with distance <= radius; widened per target when fewer than L lie inside.
        exclude_within: drop candidates with distance < exclude_within (0 disables).
    """
    T, M, device = target_pos.shape[0], cand_pos.shape[0], target_pos.device
    Ls = _per_target_counts(target_pos, cand_pos, L)
    if (target_ids is None) != (cand_ids is None):
        raise ValueError("give both target_ids and cand_ids, or neither")
    pos64 = target_pos.to(torch.float64)
    d = torch.cdist(pos64, cand_pos.to(device=device, dtype=torch.float64))  # [T, M]
    allowed = torch.ones((T, M), dtype=torch.bool, device=device)
    if target_ids is not None:
        allowed &= target_ids.to(device).view(T, 1) != cand_ids.to(device).view(1, M)
    if exclude_within > 0:
        allowed &= d >= exclude_within
    n_allowed = allowed.sum(dim=1)
    if T and int(n_allowed.min()) == 0:
        t = int(torch.argmin(n_allowed))
        raise NoNeighborsError(
            f"target {t}{'' if target_ids is None else f' (id {int(target_ids[t])})'} has no candidate neighbor "
            f"among {M} after excluding itself and candidates closer than {exclude_within:g} m"
        )
    inside = allowed if radius is None else allowed & (d <= radius)
    widened = inside.sum(dim=1) < torch.minimum(Ls, n_allowed)
    use = torch.where(widened.view(T, 1), allowed, inside)

    key = torch.where(use, d, torch.full_like(d, float("inf")))
    # Stable sort: equal distances keep candidate order (deterministic).
    order_d, order = torch.sort(key, dim=1, stable=True)
    Lmax = int(torch.minimum(Ls, use.sum(dim=1)).max()) if T else 0
    order, order_d = order[:, :Lmax], order_d[:, :Lmax]
    k = torch.arange(Lmax, device=device).view(1, Lmax)
    mask = (k < Ls.view(T, 1)) & torch.isfinite(order_d)
    index = torch.where(mask, order, torch.zeros_like(order))
    distance = torch.where(mask, order_d, torch.zeros_like(order_d)).to(target_pos.dtype)
    short = n_allowed < Ls
    return Neighbors(index=index, mask=mask, distance=distance, widened=widened, short=short)


def is_whole(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_counts(L, L_train) -> None:
    """Refuse a neighbor count that is not a whole number (``neighbors.L=2.5`` ran as 2 while the record said
    2.5), and an ``L_train`` that is not a pair of them.  A TypeError: a run's error names the setting and its
    value from the constructor's annotations (:func:`graf.errors.mistyped_setting`)."""
    pair = list(L_train) if isinstance(L_train, Sequence) and not isinstance(L_train, str) else [L_train]
    for value in (L, *pair):
        if not is_whole(value):
            raise TypeError(f"a neighbor count must be an integer, got {value!r}")
    if len(pair) != 2:
        raise TypeError(f"the training range of neighbor counts must be a pair [lo, hi], got {list(pair)}")


@defaults_from("neighbors/random_3_10.yaml")
class NeighborSelector:
    """Configured neighbor selection (``conf/neighbors/*.yaml``).

    Lengths are in wavelengths of the scene's band, so one config serves every band.

    Args:
        L: neighbors per target at evaluation (fixed, deterministic).
        L_train: inclusive range ``[lo, hi]``; at training L is drawn uniformly per target.
        radius: search radius in wavelengths (None: unlimited); widened with a warning when needed.
        exclude_within: drop candidates closer than this many wavelengths to the target.
    """

    def __init__(self, L: int, L_train: Sequence[int], radius: float | None, *, exclude_within: float):
        check_counts(L, L_train)
        lo, hi = (int(v) for v in L_train)
        if int(L) < 1 or lo < 1 or hi < lo:
            raise ConfigError(f"neighbors: need L >= 1 and 1 <= L_train[0] <= L_train[1], got L={L}, L_train={L_train}")
        if exclude_within < 0 or (radius is not None and radius <= 0):
            raise ConfigError(f"neighbors: radius must be > 0 and exclude_within >= 0, got {radius}, {exclude_within}")
        self.L, self.L_train = int(L), (lo, hi)
        self.radius, self.exclude_within = radius, float(exclude_within)

    @property
    def max_L(self) -> int:
        return max(self.L, self.L_train[1])

    def select(
        self,
        target_pos,
        cand_pos,
        wavelength: float,
        *,
        train: bool = False,
        target_ids=None,
        cand_ids=None,
        generator: torch.Generator | None = None,
        quiet: bool = False,
    ) -> Neighbors:
        """``quiet``: no warnings about widened radii or short neighbor lists (set-up checks)."""
        T = target_pos.shape[0]
        if train:
            lo, hi = self.L_train
            Ls = torch.randint(lo, hi + 1, (T,), generator=generator).to(target_pos.device)
        else:
            Ls = self.L
        result = select_neighbors(
            target_pos,
            cand_pos,
            Ls,
            target_ids=target_ids,
            cand_ids=cand_ids,
            radius=None if self.radius is None else self.radius * wavelength,
            exclude_within=self.exclude_within * wavelength,
        )
        if not train and not quiet:
            n_w, n_s = int(result.widened.sum()), int(result.short.sum())
            if n_w:
                warnings.warn(
                    f"neighbors: radius {self.radius} wavelengths held fewer than L={self.L} candidates "
                    f"for {n_w} of {T} targets; widened to the L nearest",
                    stacklevel=2,
                )
            if n_s:
                warnings.warn(
                    f"neighbors: only {int(result.counts.min())} candidates available for {n_s} of {T} "
                    f"targets (L={self.L}); using all of them",
                    stacklevel=2,
                )
        return result

    def __repr__(self) -> str:
        return (
            f"NeighborSelector(L={self.L}, L_train={list(self.L_train)}, radius={self.radius}, "
            f"exclude_within={self.exclude_within})"
        )
