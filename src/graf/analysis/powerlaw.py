"""A power law fitted on log-log axes, with its confidence interval (the interpolation theorem's check: the
error of interpolating neighbors' spectra grows as ``K * dP**2``, so its log-log slope against the largest
neighbor distance should be 2 where the law holds)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats


@dataclass(frozen=True)
class PowerLaw:
    """``y = 10**intercept * x**slope`` fitted by least squares on log10 axes over ``n`` points; ``ci``: the
    slope's two-sided confidence interval at ``level`` (Student t, n - 2 degrees of freedom)."""

    slope: float
    intercept: float
    ci: tuple[float, float]
    level: float
    n: int
    r2: float

    def __call__(self, x):
        return 10.0**self.intercept * np.asarray(x, dtype=np.float64) ** self.slope


def fit_power_law(x, y, level: float = 0.95) -> PowerLaw:
    """Fit ``log10 y = slope * log10 x + intercept``.  Points where x or y is not finite and positive are left
    out (a zero error has no logarithm); at least three must remain."""
    x, y = np.asarray(x, dtype=np.float64).ravel(), np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in length: {x.size} and {y.size}")
    keep = np.isfinite(x) & np.isfinite(y) & (x > 0) & (y > 0)
    lx, ly = np.log10(x[keep]), np.log10(y[keep])
    n = int(lx.size)
    if n < 3:
        raise ValueError(f"a power-law fit needs at least 3 positive points, got {n}")
    if np.ptp(lx) == 0:
        raise ValueError("all x are equal: the slope is undefined")
    res = stats.linregress(lx, ly)
    t = stats.t.ppf(0.5 + level / 2.0, n - 2)
    half = float(t * res.stderr)
    return PowerLaw(
        slope=float(res.slope),
        intercept=float(res.intercept),
        ci=(float(res.slope) - half, float(res.slope) + half),
        level=float(level),
        n=n,
        r2=float(res.rvalue**2),
    )
