r"""Coordinates for a posterior within a few standard deviations of a prior bound.

PyMC samples a parameter ``x ~ Uniform(a, b)`` as ``v = logit((x − a)/(b − a))``.  Near a
bound ``v`` is the log of the distance ``d`` to it, and a posterior piled against the bound
(``d`` roughly exponential with mean ``h``) has the Gumbel density
``−v − (b − a) e^{−v}/h`` there: linear towards the bound, a double-exponential wall away
from it (dielectric M0: the log density drops 50 at 3 Laplace sd along Φ_B's whitened
axis, 4.5 for a Gaussian).  Here the distance is the softplus of the sampling coordinate,

.. math:: r = c\,\mathrm{softplus}(w - 2),\qquad d = (b − a)(1 − e^{−r}),\qquad c = h/(b − a),

so ``d ≈ h e^{w}`` towards the bound and ``d ≈ h w`` away from it: an exponential pile-up
of scale ``h`` has the logistic density ``−softplus(w) − softplus(−w)`` in ``w``, with
exponential tails on both sides and no wall, and the far bound is still never crossed
(``d < b − a``).  In PyMC's coordinate ``v = σ ln(e^r − 1)`` (``σ = +1`` at a lower bound,
``−1`` at an upper one).  ``h`` is the mode's distance from the bound in PyMC's coordinates
(exactly the mean of an exponential pile-up).  :func:`bound_distance_plans` offers these
coordinates to :func:`kohpymc.reparameterization.plan` as candidates, scored like the others.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.special import expit

from kohpymc.reparameterization import (
    NUMPY,
    ArrayMath,
    Coordinates,
    Mode,
    Reparameterization,
    _whitened,
)
from kohpymc.value_space import ValueSpace

__all__ = ["BoundDistanceCoordinates", "bound_distance_plans", "near_bounds"]

#: ``w`` is shifted by this much (``softplus(w − OFFSET)``) so that the mode lies near
#: ``w = OFFSET``, not 0, where the finite-difference steps of the Laplace fit, relative to
#: ``|w|``, would vanish
OFFSET = 2.0

#: an interval parameter is sampled by its distance to a bound when its mode is closer to
#: it than this many Laplace sds (in its own units), and further from the other one
NEAR_SDS = 3.0


def _distance(w: Any, c: np.ndarray, sign: np.ndarray, xp: ArrayMath = NUMPY):
    """``v``, ``log|dv/dw|`` and ``(e, r, log(1 − e^{−r}))`` with ``e = expit(w)``."""
    r = c * xp.logaddexp(0.0, w - OFFSET)
    log_gap = xp.log(-xp.expm1(-r))  # ln(1 − e^{−r}) = ln(d/(b − a))
    v = sign * (r + log_gap)
    logjac = np.log(c) - xp.logaddexp(0.0, OFFSET - w) - log_gap
    return v, logjac, (r, log_gap)


@dataclass(frozen=True)
class BoundDistanceCoordinates(Coordinates):
    r"""Coordinates with some interval elements sampled by their distance to a bound.

    :class:`~kohpymc.reparameterization.Coordinates`, except that the elements ``near``
    are the softplus of their distance to a bound (module docstring).

    Attributes
    ----------
    near : ndarray of bool
        The elements so sampled (never also ``log_scale``).
    sign : ndarray
        ``+1`` where the bound is the lower one, ``−1`` where it is the upper.
    share : ndarray
        ``c = h/(b − a)``, the distance scale as a share of the prior width.

    Examples
    --------
    >>> coords = BoundDistanceCoordinates(
    ...     np.zeros(1, bool), np.array([0.0]), np.array([1.0]),
    ...     near=np.ones(1, bool), sign=np.array([-1.0]), share=np.array([0.01]))
    >>> v = coords.to_value(np.array([2.0]))[0]  # w = 2: ln 2 shares from the upper bound
    >>> round(float(1 - expit(v[0])), 6)
    0.006908
    >>> round(float(coords.from_value(v)[0]), 9)
    2.0
    """

    near: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    sign: np.ndarray = field(default_factory=lambda: np.zeros(0))
    share: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def kind_prefix(self) -> str:
        """``"bound-distance-"``, prefixed to the kind of a plan in these coordinates."""
        return "bound-distance-"

    def to_value(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``v(w)``, ``dv/dw``, ``d log|dv/dw| / dw`` and ``Σ log|dv/dw|``."""
        v, dv, dlogjac, logjac = super().to_value(w)
        m = self.near
        if not m.any() or not np.isfinite(logjac):
            return v, dv, dlogjac, logjac
        w_m, c = np.asarray(w, float)[m], self.share[m]
        v[m], jac, (r, _) = _distance(w_m, c, self.sign[m])
        e = expit(w_m - OFFSET)
        dv[m] = self.sign[m] * np.exp(jac)
        dlogjac[m] = 1.0 - e - c * e / np.expm1(r)
        return v, dv, dlogjac, logjac + float(np.sum(jac))

    def value_and_log_jacobian(self, w: Any, xp: ArrayMath = NUMPY) -> tuple[Any, Any]:
        """``v(w)`` and ``Σ log|dv/dw|``, over ``xp`` (numpy or PyTensor)."""
        v, logjac = super().value_and_log_jacobian(w, xp)
        m = self.near
        if not m.any():
            return v, logjac
        index = np.flatnonzero(m)
        v_m, jac, _ = _distance(w[index], self.share[m], self.sign[m], xp)
        return xp.put(xp.copy(v), index, v_m), logjac + xp.sum(jac)

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """``w(v)``: the inverse of the elementwise map, then of the shares and the ridge."""
        plain = replace(self, shares=None, ridge=None)
        w = super(BoundDistanceCoordinates, plain).from_value(np.asarray(v, float))
        m = self.near
        if m.any():
            r = np.logaddexp(0.0, self.sign[m] * np.asarray(v, float)[m])
            q = np.maximum(r / self.share[m], 1e-300)
            w[m] = OFFSET + q + np.log(-np.expm1(-q))  # softplus⁻¹
        w = w if self.shares is None else self.shares.inverse(w)
        return w if self.ridge is None else self.ridge.inverse(self, w)


def near_bounds(
    space: ValueSpace, mode: np.ndarray, value_sd: np.ndarray, n_sds: float = NEAR_SDS
) -> tuple[np.ndarray, np.ndarray]:
    """Interval elements whose mode lies within ``n_sds`` Laplace sds of one bound only.

    Returns the mask and the sign (``+1`` lower bound, ``−1`` upper).  Distances and sds
    are in the parameter's own units (the Laplace sd carried by the interval transform).
    """
    kinds = np.array(space.transforms)
    finite = np.isfinite(space.lower) & np.isfinite(space.upper)
    mask = np.zeros(space.ndim, bool)
    sign = np.zeros(space.ndim)
    for i in np.flatnonzero((kinds == "interval") & finite & np.isfinite(value_sd)):
        width = space.upper[i] - space.lower[i]
        s = float(expit(mode[i]))
        sd = width * s * (1.0 - s) * float(value_sd[i])
        below, above = width * s, width * (1.0 - s)  # x − a, b − x
        if below < n_sds * sd < above:
            mask[i], sign[i] = True, 1.0
        elif above < n_sds * sd < below:
            mask[i], sign[i] = True, -1.0
    return mask, sign


def _coordinates(space: ValueSpace, plan: Reparameterization, mode: Mode):
    """``plan``'s elementwise coordinates with its near-bound elements by distance (or None)."""
    coords = plan.coordinates
    if coords.walls or coords.ridge is not None or plan.value_sd is None:
        return None
    if type(coords) is not Coordinates:
        return None
    mask, sign = near_bounds(space, mode.value, plan.value_sd)
    if not mask.any():
        return None
    s = expit(sign * mode.value)  # the mode's distance from the bound, as a share
    return BoundDistanceCoordinates(
        coords.log_scale & ~mask, coords.lower, coords.upper, coords.walls, coords.shares,
        near=mask, sign=sign, share=np.where(mask, s, 1.0),
    )  # fmt: skip


def bound_distance_plans(
    space: ValueSpace, plans: Sequence[Reparameterization], mode: Mode
) -> list[Reparameterization]:
    """Each plan's coordinates with the near-bound elements sampled by their distance.

    For the whitened plans (no walls, no bound ridge) with an interval element whose mode
    lies within :data:`NEAR_SDS` Laplace sds of a bound; the kind is prefixed
    ``"bound-distance-"``.

    Examples
    --------
    >>> plans = bound_distance_plans(space, plans, mode)  # doctest: +SKIP
    """
    out = []
    for plan in plans:
        coords = _coordinates(space, plan, mode)
        found = None if coords is None else _whitened(space, coords, mode.value, mode)
        if found is not None:
            out.append(found)
    return out
