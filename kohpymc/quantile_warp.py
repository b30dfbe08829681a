"""A sampling coordinate warped so that a one-dimensional profile's quantiles are normal.

A plan whose leading coordinate follows a profile that no affine map makes Gaussian (the
log of a noise sd, with a wall on one side; a ridge's pivot bounded by the data on one
side only) samples ``y`` with ``x = W(y)``: a cubic spline through the points where the
profile's CDF equals the standard normal CDF at ``y_k ∈ [−5, 5]``, linear beyond.  Its
derivative is the log-Jacobian the plan adds, so the density stays exact.  Used by
:mod:`kohpymc.funnel` and :mod:`kohpymc.ridge_curve`.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize, stats
from scipy.interpolate import CubicSpline

__all__ = ["NODES", "spline_through_quantiles", "unwarped", "warped"]

#: standard-normal quantiles at which the warp matches the profile's
NODES = np.linspace(-5.0, 5.0, 41)


def spline_through_quantiles(cdf: np.ndarray, grid: np.ndarray) -> CubicSpline | None:
    """``W`` with ``F(W(y_k)) = Φ(y_k)`` at :data:`NODES`, or None when not increasing.

    ``cdf`` is the profile's CDF on ``grid`` (increasing, from 0 to 1).

    Examples
    --------
    >>> grid = np.linspace(-12.0, 12.0, 6001)
    >>> warp = spline_through_quantiles(stats.norm.cdf(grid, scale=2.0), grid)
    >>> round(float(warp(1.0)), 6)  # N(0, 2²): x = 2 y
    2.0
    """
    warp = CubicSpline(NODES, np.interp(stats.norm.cdf(NODES), cdf, grid))
    if not np.all(warp(np.linspace(NODES[0], NODES[-1], 2001), 1) > 0):
        return None
    return warp


def warped(warp: CubicSpline | None, centre: float, scale: float, y: float):
    """``x(y)`` and its first two derivatives: ``centre + scale·y``, or ``W(y)`` with ``warp``.

    Examples
    --------
    >>> warped(None, 1.0, 2.0, 0.5)
    (2.0, 2.0, 0.0)
    """
    if warp is None:
        return centre + scale * y, scale, 0.0
    end = float(warp.x[-1])
    if abs(y) <= end:
        return float(warp(y)), float(warp(y, 1)), float(warp(y, 2))
    edge = float(np.sign(y)) * end  # linear beyond the nodes
    slope = float(warp(edge, 1))
    return float(warp(edge)) + slope * (y - edge), slope, 0.0


def unwarped(warp: CubicSpline | None, centre: float, scale: float, x: float) -> float:
    """The inverse of :func:`warped`.

    Examples
    --------
    >>> unwarped(None, 1.0, 2.0, 2.0)
    0.5
    """
    if warp is None:
        return (x - centre) / scale
    gap = lambda y: warped(warp, centre, scale, y)[0] - x  # noqa: E731
    return float(optimize.brentq(gap, -1e3, 1e3, xtol=1e-13))
