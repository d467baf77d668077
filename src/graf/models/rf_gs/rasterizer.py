"""The rasterizer of RF Gaussian splatting: axis-aligned 2-D Gaussians on the spectrum grid, summed.

The grid is :mod:`graf.geometry.grid`'s: row r is elevation ``E_r = r + 1`` deg (1..90), column c azimuth
``A_c = c + 1`` deg (1..360).  Gaussian k has a mean ``(e_k, a_k)`` (deg), widths ``(s_k, t_k)`` (deg, in
elevation and azimuth) and an amplitude ``w_k`` (signed); its value at pixel (r, c) is

    ``w_k * exp(-(E_r - e_k)^2 / (2 s_k^2)) * P(A_c - a_k; t_k)``,

and the spectrum is the sum over k (no depth order, no alpha compositing: the spectrum is a received power
pattern, not an occluding view; SwiftWRF sums too).

* **Azimuth wraps.**  ``P(d; t) = exp(-n^2 / (2 t^2)) + exp(-(360 - n)^2 / (2 t^2))`` with ``n`` the angular
  distance ``|d|`` wrapped into [0, 180]: the wrapped normal over its two nearest turns, so a Gaussian at 359.5 deg
  lights column 0 (azimuth 1 deg) as one at 0.5 deg lights column 358 (359 deg), and the profile is smooth across
  the seam.  The turns left out are at least 360 deg away: they weigh at most ``exp(-(360 / t)^2 / 2)`` of the
  amplitude, below 2e-8 up to ``t = 60`` deg, the widest the module allows.  The second turn is computed only for
  the Gaussians wider than :data:`WIDE` deg (for the others it is below 1e-11).
* **Elevation ends.**  The grid stops at 0.5 and 90.5 deg (the edges of its first and last rows); nothing wraps
  there.  A Gaussian whose mean is at an edge shows the half of it that lies on the grid.  The zenith (90 deg) is
  a pole of the sphere, where every azimuth is one direction; the Gaussians live in the image plane, as
  SwiftWRF's do, so an azimuth width in degrees stays one at every elevation (on the sphere a Gaussian near the
  zenith would widen as ``1 / cos(elevation)`` in azimuth degrees).  Nothing makes the top row, one direction,
  constant: the model learns it from the data as any other row, and Gaussians wide in azimuth can represent it.
* **Separable.**  Axis-aligned Gaussians factor into an elevation profile ``U [90, N]`` and an azimuth profile
  ``V [360, N]``, so a spectrum is one matrix product ``S = U diag(w) V^T`` (exact, no cutoff): about
  ``90 * 360 * N`` multiply-adds (33 M at N = 1,024), the same code on a CPU and a GPU, and autograd gives the
  backward.
* Every exponent is floored at :data:`EXP_FLOOR` (-60: a value of ``1e-26`` where it would be smaller):
  arguments below about -87 underflow to zero, and torch's CPU ``exp`` leaves its vectorised path for them.
* The profiles are computed in float32 (also under autocast); the matrix product follows autocast (bfloat16
  under a bf16 autocast) and the spectrum is returned as float32.
"""

from __future__ import annotations

import torch

from graf.geometry.grid import N_AZIMUTH, N_ELEVATION

EXP_FLOOR = -60.0
ELEVATION_EDGES = (0.5, N_ELEVATION + 0.5)  # deg: the grid's lower and upper edge (no wrap)
WIDE = 25.0  # deg: an azimuth width above which the wrapped normal's second turn is computed
SIGMA_LIMIT = 60.0  # deg: the widest Gaussian the two turns render to 2e-8


def grid_angles(device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(elevations [90], azimuths [360])`` of the grid's rows and columns, in degrees (float32)."""
    el = torch.arange(1, N_ELEVATION + 1, device=device, dtype=torch.float32)
    az = torch.arange(1, N_AZIMUTH + 1, device=device, dtype=torch.float32)
    return el, az


def wrapped_distance(x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """The angular distance ``|x - mean|`` wrapped into [0, 180] degrees (``x`` in [0, 360], any ``mean``)."""
    a = x - torch.remainder(mean, 360.0)  # in (-360, 360]: the mean reduced first, where it is small
    if _in_place(a):
        return a.abs_().sub_(180.0).abs_().neg_().add_(180.0)
    return 180.0 - (a.abs() - 180.0).abs()  # min(|a|, 360 - |a|), without torch.minimum (slow on CPU)


def _in_place(*tensors: torch.Tensor) -> bool:
    """Whether no gradient flows through ``tensors``: the profiles are then computed in place (the same arithmetic
    without a fresh ``[B, 360, N]`` tensor per operation, each of which a CPU must fault in page by page)."""
    return not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))


def _gauss(d: torch.Tensor, sigma: torch.Tensor, own: bool = False) -> torch.Tensor:
    """``exp(max(-d^2 / (2 sigma^2), EXP_FLOOR))``; in place on ``d`` when the caller owns it (``own``: made for
    this call and not read again) and no gradient flows."""
    c = -0.5 / sigma.square()
    if own and _in_place(d, c):
        return d.square_().mul_(c).clamp_min_(EXP_FLOOR).exp_()
    return torch.exp((d.square() * c).clamp_min(EXP_FLOOR))


def _distance(grid: torch.Tensor, mean: torch.Tensor, kind: str) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(u, sign)``: the distance ``[B, R, N]`` a profile's Gaussian is of, from ``grid [R]`` to ``mean [B, N]``.
    ``plain``: ``grid - mean``; ``near``: the same wrapped into [-180, 180] (the nearest turn); ``far``:
    ``360 - |near|`` (the second-nearest turn), with ``sign`` the sign of the near distance (``du/dmean``)."""
    if kind == "plain":
        return grid[None, :, None] - mean[:, None, :], None
    u = grid[None, :, None] - torch.remainder(mean, 360.0)[:, None, :]  # the mean reduced first, where it is small
    u = u.sub_(torch.round(u * (1.0 / 360.0)).mul_(360.0))  # (-360, 360] -> [-180, 180]: cheaper than remainder_
    if kind == "near":
        return u, None
    sign = torch.sign(u)
    return u.abs_().neg_().add_(360.0), sign


class _Profile(torch.autograd.Function):
    """``exp(max(-u^2 / (2 sigma^2), EXP_FLOOR))`` of :func:`_distance`, ``[B, R, N]``, with its backward written out:
    the gradients of the means and widths are sums over the grid of ``G g u / sigma^2`` and ``G g u^2 / sigma^3``
    (times ``-sign`` for the far turn), a few passes over ``[B, R, N]`` where autograd's chain of elementwise
    operations takes about twenty (it was 80% of a training step's time).  Where the exponent is floored
    (``g = e^-60``, about 1e-26) the gradient is that small value's, not autograd's zero."""

    @staticmethod
    def forward(ctx, grid, mean, sigma, kind: str):
        u, sign = _distance(grid, mean, kind)
        c = (-0.5 / sigma.square())[:, None, :]
        g = torch.mul(u, u).mul_(c).clamp_min_(EXP_FLOOR).exp_()
        ctx.save_for_backward(u, g, sigma, sign if sign is not None else torch.empty(0))
        ctx.kind = kind
        return g

    @staticmethod
    def backward(ctx, grad):
        u, g, sigma, sign = ctx.saved_tensors
        t = grad * g  # [B, R, N]
        inv = 1.0 / sigma.square()
        if ctx.kind == "far":
            d_mean = (t * u * sign).sum(1).mul_(-inv)
        else:
            d_mean = None
        t = t.mul_(u)
        if d_mean is None:
            d_mean = t.sum(1).mul_(inv)
        d_sigma = t.mul_(u).sum(1).mul_(inv / sigma)
        return None, d_mean, d_sigma, None


def _profile(grid: torch.Tensor, mean: torch.Tensor, sigma: torch.Tensor, kind: str) -> torch.Tensor:
    """A Gaussian profile ``[B, R, N]`` over ``grid`` (:class:`_Profile`; where no gradient flows, computed in
    place from the unsigned distance of :func:`wrapped_distance`, the cheaper one)."""
    if not _in_place(mean, sigma):
        return _Profile.apply(grid, mean, sigma, kind)
    if kind == "plain":
        d = grid[None, :, None] - mean[:, None, :]
    else:
        d = wrapped_distance(grid[None, :, None], mean[:, None, :])
        if kind == "far":
            d = d.neg_().add_(360.0)
    return _gauss(d, sigma[:, None, :], own=True)


def elevation_profiles(mean: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """``[B, 90, N]``: ``exp(-(E_r - mean)^2 / (2 sigma^2))`` for means and widths ``[B, N]`` (deg)."""
    el, _ = grid_angles(mean.device)
    return _profile(el.to(mean.dtype), mean, sigma, "plain")


def azimuth_profiles(mean: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """``[B, 360, N]``: the wrapped normal ``P(A_c - mean; sigma)`` for means and widths ``[B, N]`` (deg)."""
    _, az = grid_angles(mean.device)
    az = az.to(mean.dtype)
    wide = torch.nonzero(sigma.detach().amax(0) > WIDE).flatten()
    out = _profile(az, mean, sigma, "near")
    if not wide.numel():
        return out
    return out.index_add(2, wide, _profile(az, mean[:, wide], sigma[:, wide], "far"))


def render(elevation, azimuth, sigma_el, sigma_az, amplitude) -> torch.Tensor:
    """Spectra ``[B, 90, 360]`` (float32) of the Gaussians given as ``[B, N]`` tensors: means (deg), widths (deg)
    and amplitudes.  ``S_b = U_b diag(w_b) V_b^T``."""
    with torch.autocast(device_type=elevation.device.type, enabled=False):
        u = elevation_profiles(elevation.float(), sigma_el.float()) * amplitude.float()[:, None, :]
        v = azimuth_profiles(azimuth.float(), sigma_az.float())
    return torch.matmul(u, v.transpose(1, 2)).float()


def render_dense(elevation, azimuth, sigma_el, sigma_az, amplitude) -> torch.Tensor:
    """The same spectra summed Gaussian by Gaussian over the full grid, both turns for every Gaussian (no
    factorisation): ``[B, N, 90, 360]`` in memory, for checks on a few Gaussians."""
    el, az = grid_angles(elevation.device)
    de = el[None, None, :, None] - elevation[:, :, None, None]
    near = wrapped_distance(az[None, None, None, :], azimuth[:, :, None, None])
    se, sa = sigma_el[:, :, None, None], sigma_az[:, :, None, None]
    pa = _gauss(near, sa) + _gauss(360.0 - near, sa)
    return (amplitude[:, :, None, None] * _gauss(de, se) * pa).sum(1)
