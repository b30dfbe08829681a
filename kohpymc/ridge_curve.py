r"""Sampling along a curved ridge that runs between the faces of the prior box.

When the data fix a power law of bounded positive parameters (the dielectric stand-in's
Fowler–Nordheim exponent ``B ∝ √m*·Φ_B^{3/2}``, fixed to 10⁻⁴ while Φ_B spans its prior
box), the posterior is a thin ridge from one face of the box to the other.  Along it the
other parameters' conditional modes and scales change by hundreds of the Laplace standard
deviations at the mode, so no affine map fitted there fits the ridge (Gaussian score
20–35), and a straight segment (:class:`~kohpymc.reparameterization.BoxRidgePlan`) with
walled log coordinates leaves holes of zero density inside the typical set wherever a
parameter near its own bound crosses its wall (M2: 5 % of standard-normal points).

:class:`RidgeCurvePlan` follows the ridge over its whole length.  The *pivot* ``p`` (the
bounded parameter that leads the ridge's flattest direction) is sampled as the logit of
its position on the log scale between its bounds, ``s = expit(w_p) ∈ (0, 1)``, so every
value of its coordinate is inside the box; the other coordinates are

.. math:: w_r = c(s) + L(s)\,y,

with ``c(s)`` a cubic spline through the conditional modes at ``K`` nodes from face to
face and ``L(s)`` a spline through the Cholesky factors of the conditional Laplace
covariances there.  The map is triangular: ``log|∂w/∂z| = log σ_p + log det L(s)``, whose
gradient in ``t`` is carried exactly.  The other bounded parameters are sampled in their
own units through a soft box (:class:`SoftBoxCoordinates`), where linear trade-offs
between them stay straight (in the logit of a parameter 1.6 sd from its bound, a partner
that compensates it linearly bends exponentially).  Where a soft-box parameter lies within
a few sds of a bound, its partners are measured from their regression on what the box
leaves of it (a :class:`~kohpymc.reparameterization.BoundRidge`), so that past the bound
they stop with it instead of running into a wall of their conditional precision.

Without a log scale (no interval prior on the positive axis: Steinhart–Hart's
``C ∈ (−5·10⁻⁷, 5·10⁻⁷)``, ``A`` and ``B`` bounded below by 0) the pivot is an interval
parameter in its own units, ``s`` its position between its bounds (PyMC's logit), the
members staying in PyMC's coordinates (``own=True``, kind
``"ridge-curve-own-units-soft-box"``); the nodes are then refined where the splines miss
the ridge (:func:`_refined`).  Steinhart–Hart with an input-dependent discrepancy (M3),
where the straight segment's line missed the curved ridge by 11 transverse sds at 3 of its
sds: r̂ 1.051 → 1.007, bulk ESS 37 → 705, divergences 39 → 16 in 2 × 1000 draws.

Where the pivot's axis fits badly (its drop at ±1.5 off a Gaussian's by more than
``_WARP_ERROR``), the pivot is warped to the normal quantiles of its Laplace marginal
(:func:`_pivot_warp`), in its own units too.  Steinhart–Hart under a stationary GP
discrepancy (M4): below C ≈ −10⁻⁷ the GP must take up the physics' misfit, and the
posterior ends in a wall along C (log density 20 down at −2 along the affine pivot, the
second derivative ±540 within its ±3); the bends fitted on top of that map left the wall
with a kink (Hessian eigenvalues up to 10⁴ in ``z`` at posterior draws).  Warped, the
pivot's axis drops 2.0 and 8.0 at ±2 and ±4 and no bend is needed (score 0.64 → 0.23);
4 × 1000 draws at target 0.95: 85 → 21 (seed 3) and 97 → 33 (seed 2) divergent transitions,
293 → 76 and 148 → 61 s of sampling; after the second run at 0.99, 26 → 13 and 32 → 4,
with 193–201 → 32 leapfrog steps per draw.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
from scipy import optimize
from scipy.interpolate import CubicSpline
from scipy.linalg import solve_triangular
from scipy.special import expit, logit

from kohpymc.quantile_warp import spline_through_quantiles, unwarped, warped
from kohpymc.reparameterization import (
    BoundRidge,
    Coordinates,
    Mode,
    Reparameterization,
    _axis_errors,
    _gaussian_score,
    _hessian,
    _inverse_cholesky,
    _laplace,
)
from kohpymc.value_space import ValueSpace

__all__ = ["ChainedBoundRidge", "RidgeCurvePlan", "SoftBoxCoordinates", "ridge_curve_plan"]

#: marginal over conditional Laplace sd of the pivot above which a ridge is followed
_RIDGE_RATIO = 10.0

#: soft-box width as a fraction of the Laplace sd in the parameter's own units
_SOFT_WIDTH = 0.5


def _log_gap(u: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``ln(softplus(u) − softplus(u − c))`` for ``c > 0``, without cancellation."""
    return np.log(np.log1p(-np.expm1(-c) / (np.exp(-u) + np.exp(-c))))


@dataclass(frozen=True)
class SoftBoxCoordinates(Coordinates):
    r"""Bounded parameters in their own units, squeezed into their box near the faces.

    For the elements ``soft``, ``x = a + h·[softplus((ξ − a)/h) − softplus((ξ − b)/h)]``:
    ``x ≈ ξ`` more than a few ``h`` inside the bounds, and the density decays like
    ``e^{−|ξ − bound|/h}`` beyond them (no wall, no zero-density hole).  ``h`` (``width``)
    is a fraction of the posterior sd, so the map is the identity where the posterior
    lives unless it lies against a face.  The other elements follow
    :class:`~kohpymc.reparameterization.Coordinates` (log-logit where ``log_scale``).

    Examples
    --------
    >>> coords = SoftBoxCoordinates(np.zeros(1, bool), np.array([0.0]), np.array([1.0]),
    ...                             soft=np.ones(1, bool), width=np.array([0.01]))
    >>> v = coords.to_value(np.array([0.3]))[0]
    >>> round(float(1 / (1 + np.exp(-v[0]))), 6)  # x = 0.3, well inside
    0.3
    >>> round(float(coords.from_value(v)[0]), 6)
    0.3
    """

    soft: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    width: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def name(self) -> str:
        """``"soft-box"``."""
        return "soft-box"

    def to_value(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``v(w)``, ``dv/dw``, ``d log|dv/dw| / dw`` and ``Σ log|dv/dw|``."""
        v, dv, dlogjac, logjac = super().to_value(w)
        m = self.soft
        if not m.any() or not np.isfinite(logjac):
            return v, dv, dlogjac, logjac
        a, b, h = self.lower[m], self.upper[m], self.width[m]
        c = (b - a) / h
        p = (np.asarray(w, float)[m] - a) / h
        with np.errstate(all="ignore"):
            log_above, log_below = _log_gap(p, c), _log_gap(c - p, c)  # ln((x−a)/h), ln((b−x)/h)
            slope = expit(p) - expit(p - c)  # dx/dξ
            curvature = (expit(p) * expit(-p) - expit(p - c) * expit(c - p)) / h
            above, below = h * np.exp(log_above), h * np.exp(log_below)
            v[m] = log_above - log_below
            dv[m] = (b - a) * slope / (above * below)
            dlogjac[m] = curvature / slope - slope / above + slope / below
            soft_logjac = float(np.sum(np.log(dv[m])))
        return v, dv, dlogjac, logjac + soft_logjac

    def value_and_log_jacobian(self, w: Any, xp: Any = None) -> tuple[Any, Any]:
        """Numpy only: ``v(w)`` and ``Σ log|dv/dw|`` (no symbolic form)."""
        v, _, _, logjac = self.to_value(np.asarray(w, float))
        return v, logjac

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """``w(v)``: the inverse of the elementwise map, then of the shares and the ridge."""
        w = Coordinates.from_value(self.elementwise(), v)
        m = self.soft
        if m.any():
            a, b, h = self.lower[m], self.upper[m], self.width[m]
            c = (b - a) / h
            gap = np.clip((b - a) * expit(np.asarray(v, float)[m]) / h, 1e-300, c * (1 - 1e-15))
            w[m] = a + h * (np.log(np.expm1(gap)) - np.log(-np.expm1(gap - c)))
        w = w if self.shares is None else self.shares.inverse(w)
        return w if self.ridge is None else self.ridge.inverse(self, w)


@dataclass(frozen=True)
class RidgeCurvePlan(Reparameterization):
    r"""Sampling coordinates ``z = (t, y)`` along a curved ridge (see the module docstring).

    ``w_p = centre + scale·t``, or ``w_p = W(t)`` with ``warp`` (a spline matching the
    quantiles of the pivot's Laplace marginal to a standard normal's, linear beyond its
    nodes); ``s = expit(w_p)``, ``w_r = c(s) + L(s) y``; then the elementwise map of
    ``coordinates`` (a :class:`SoftBoxCoordinates`).  ``nodes`` are the ``s`` of the
    splines; beyond the first and last node (within 10⁻⁶ of the faces) ``c`` and ``L``
    are held constant.
    """

    symbolic: ClassVar[bool] = False  # its own map, in numpy only
    #: splines fitted at a few nodes: between and beyond them the curvature in ``z`` is not
    #: the nodes', so NUTS takes smaller steps (:data:`kohpymc.sampling.CURVED_TARGET_ACCEPT`).
    #: Steinhart–Hart M1/M2 (4 chains × 1000, seeds 2 and 3): 1 and 2 divergent transitions
    #: at 0.9 (seed 2), none in all four runs at 0.95, in the same wall time
    curved: ClassVar[bool] = True

    pivot: int = 0
    rest: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    centre: float = 0.0
    scale: float = 1.0
    nodes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    curve: Any = None
    factor: Any = None
    warp: Any = None

    def _pivot_of(self, t: float) -> tuple[float, float, float]:
        """``w_p(t)`` and its first two derivatives (affine, or the warp's spline)."""
        return warped(self.warp, self.centre, self.scale, t)

    def _t_of(self, w_pivot: float) -> float:
        """The inverse of :meth:`_pivot_of`."""
        return unwarped(self.warp, self.centre, self.scale, w_pivot)

    def _factor(self, s: float) -> tuple[Any, Any, np.ndarray, np.ndarray, float, float]:
        """``c(s)``, ``L(s)`` and their ``s``-derivatives, ``log det L(s)`` and its derivative."""
        lo, hi = self.nodes[0], self.nodes[-1]
        inside = lo < s < hi
        sc = min(max(s, lo), hi)
        n = self.rest.size
        c, entries = self.curve(sc), self.factor(sc)
        dc = self.curve(sc, 1) if inside else np.zeros(n)
        dentries = self.factor(sc, 1) if inside else np.zeros_like(entries)
        return (c, dc, *lower_factor(entries, dentries, n))

    def _position(self, z: np.ndarray):
        z = np.asarray(z, float)
        w = np.empty(z.size)
        w[self.pivot], slope, bend = self._pivot_of(float(z[0]))
        s = float(expit(w[self.pivot]))
        c, dc, chol, dchol, logdet, dlogdet = self._factor(s)
        w[self.rest] = c + chol @ z[1:]
        # the warp's log-Jacobian and its t-derivative (0 and 0 for the affine pivot)
        warped = (0.0, 0.0) if self.warp is None else (np.log(slope), bend / slope)
        return w, s, dc + dchol @ z[1:], chol, logdet, dlogdet, slope, warped

    def to_value(self, z: np.ndarray) -> np.ndarray:
        """PyMC value-space vector of sampling coordinates ``z``."""
        return self.coordinates.to_value(self._unshared(self._position(z)[0]))[0]

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector."""
        w = self.coordinates.from_value(np.asarray(v, float))
        s = float(expit(w[self.pivot]))
        c, _, chol, _, _, _ = self._factor(s)
        y = solve_triangular(chol, w[self.rest] - c, lower=True)
        return np.append(self._t_of(float(w[self.pivot])), y)

    def laplace_value_sd(self) -> np.ndarray:  # pragma: no cover - not a Laplace map
        """NaN: the map is not one Laplace covariance."""
        return np.full(self.ndim, np.nan)

    def logp_dlogp(
        self, space: ValueSpace, z: np.ndarray, *, safe: bool = False
    ) -> tuple[float, np.ndarray]:
        """Log density of ``z`` (exact up to a constant) and its gradient."""
        w, s, dw_ds, chol, logdet, dlogdet, slope, warped = self._position(z)
        v, dv, dlogjac, logjac = self.coordinates.to_value(self._unshared(w))
        if not np.isfinite(logjac):
            return -np.inf, np.zeros(self.ndim)
        logp, grad_v = space.logp_dlogp_or_nan(v) if safe else space.logp_dlogp(v)
        g = self._pull_back(w, grad_v * dv + dlogjac)
        g_rest = g[self.rest]
        along = g[self.pivot] + s * (1.0 - s) * (float(dw_ds @ g_rest) + dlogdet)
        logp = logp + logjac + logdet + warped[0]
        return logp, np.append(slope * along + warped[1], chol.T @ g_rest)


def lower_factor(
    entries: np.ndarray, dentries: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """A lower-triangular factor from its splined entries, and its derivative.

    ``entries`` holds the log of the diagonal (first ``n``), then the strict lower
    triangle row by row; ``dentries`` their derivatives along the path.  Returns
    ``(L, dL, ln det L, d ln det L)``.

    Examples
    --------
    >>> L, dL, logdet, _ = lower_factor(np.array([0.0, np.log(2.0), 0.5]), np.zeros(3), 2)
    >>> L.tolist(), round(logdet, 6)
    ([[1.0, 0.0], [0.5, 2.0]], 0.693147)
    """
    lower = np.tril_indices(n, -1)
    diag = np.exp(entries[:n])
    chol, dchol = np.zeros((n, n)), np.zeros((n, n))
    chol[np.diag_indices(n)], dchol[np.diag_indices(n)] = diag, diag * dentries[:n]
    chol[lower], dchol[lower] = entries[n:], dentries[n:]
    return chol, dchol, float(entries[:n].sum()), float(dentries[:n].sum())


def _nodes(n: int, end: float = 1e-6) -> np.ndarray:
    """``n`` Chebyshev–Lobatto positions in (0, 1), the ends moved ``end`` inside."""
    s = 0.5 * (1.0 - np.cos(np.pi * np.arange(n) / (n - 1)))
    s[0], s[-1] = end, 1.0 - end
    return s


def _ridge_members(
    laplace: Reparameterization,
    candidates: np.ndarray | None = None,
    min_ratio: float = _RIDGE_RATIO,
) -> tuple[int, np.ndarray] | None:
    """The pivot and the ridge's members, or None without a long ridge.

    Without ``candidates`` the ridge is the flattest direction ``d`` of the Laplace
    precision in the log-logit coordinates; the pivot is its largest log-logit component,
    the members those with at least a tenth of it.  With ``candidates`` (a mask; elements
    on different scales, where the flattest direction of the precision is that of the
    widest element, not the ridge's) the pivot is the candidate whose marginal sd exceeds
    its conditional sd the most, the members every candidate whose ratio exceeds
    ``_RIDGE_RATIO``.  A ridge is long when the pivot's marginal sd is more than
    ``min_ratio`` (default ``_RIDGE_RATIO``) times its conditional sd.
    """
    coords = laplace.coordinates
    log = coords.log_scale if candidates is None else candidates
    if coords.walls or coords.ridge is not None or log.sum() < 2:
        return None
    cov = laplace.chol @ laplace.chol.T
    precision = np.linalg.inv(cov)
    ratio = np.sqrt(np.diag(cov) * np.diag(precision))
    if candidates is not None:
        ratio = np.where(candidates, ratio, 0.0)
        pivot = int(np.argmax(ratio))
        members = np.flatnonzero(ratio > _RIDGE_RATIO)
        return (pivot, members) if ratio[pivot] > _RIDGE_RATIO else None
    if min_ratio < _RIDGE_RATIO:
        # the widest direction among the log-scale elements (the flattest of the whole
        # precision can be another element's own: a constant bias in units of the output)
        block = np.flatnonzero(log)
        d = np.zeros(log.size)
        d[block] = np.abs(np.linalg.eigh(cov[np.ix_(block, block)])[1][:, -1])
    else:
        lam, vec = np.linalg.eigh(precision)
        d = np.where(log, np.abs(vec[:, 0]), 0.0)
    pivot = int(np.argmax(d))
    if not d[pivot] > 0.0 or ratio[pivot] < min_ratio:
        # d[pivot] = 0: the flattest direction is another element's alone (an
        # uninformed discrepancy coefficient), not a ridge of the log-scale elements
        return None
    members = log & (d >= 0.1 * d[pivot])
    if min_ratio < _RIDGE_RATIO:
        # a short ridge: its flattest direction is the pivot's own when the pivot's scale
        # dominates, so the members are the log-scale elements correlated with it too
        members |= log & (ratio >= min_ratio)
    return pivot, np.flatnonzero(members)


def _soft_box(
    space: ValueSpace, laplace: Reparameterization, members: np.ndarray, *, own: bool = False
):
    """The ridge's members log-logit, every other interval parameter in a soft box.

    With ``own`` the members keep PyMC's coordinates (the logit of their own units).
    """
    coords = laplace.coordinates
    interval = space.bounded_intervals()
    on_ridge = np.zeros(space.ndim, bool)
    on_ridge[members] = True
    log_scale = np.zeros(space.ndim, bool) if own else on_ridge
    soft = interval & ~on_ridge
    share = expit(np.asarray(laplace.mode.value if laplace.mode else laplace.mean, float))
    own_sd = (space.upper - space.lower) * share * (1.0 - share) * laplace.value_sd
    width = np.where(soft, _SOFT_WIDTH * own_sd, 1.0)
    if not np.all(np.isfinite(width[soft]) & (width[soft] > 0)):
        return None
    return SoftBoxCoordinates(
        log_scale, space.lower.copy(), space.upper.copy(), shares=coords.shares,
        soft=soft, width=width,
    )  # fmt: skip


#: a soft-box parameter whose mode lies within this many Laplace sds of one bound gets
#: partners that follow what the box leaves of it (far from the bound the correction
#: vanishes, so a generous reach costs nothing; dielectric M2's E_A, 3.3 sds below its
#: upper bound, is reached once the ε_∞–E_A parabola is bent: 42 divergences there)
_SOFT_NEAR_SDS = 6.0


@dataclass(frozen=True)
class ChainedBoundRidge(BoundRidge):
    r"""A bound ridge whose bounded elements also follow each other, in order.

    A :class:`~kohpymc.reparameterization.BoundRidge` generalised to chained elements.

    Element ``b_k``'s bend (its value in its own units less its tangent at the mode) moves
    every coordinate except ``b_0 … b_k`` by ``beta[:, k]``, the regression on ``x_{b_k}``
    given ``b_0 … b_{k−1}``; ``b_k`` is bent where the earlier ones left it.  The map is
    unit-triangular (no Jacobian term) and its inverse explicit: each ``b_k`` keeps its
    final value from step ``k`` on.  ``others`` is every index; ``beta`` is ``(n, |B|)``.

    Examples
    --------
    >>> from kohpymc.reparameterization import Coordinates
    >>> coords = Coordinates.identity(3)
    >>> cov = np.array([[1.0, 0.9, 0.5], [0.9, 1.0, 0.5], [0.5, 0.5, 1.0]])
    >>> ridge = ChainedBoundRidge.fit(coords, np.array([4.0, -4.0, 0.0]), cov,
    ...                               np.array([0, 1]), (np.zeros(2), np.ones(2)))
    >>> u = np.array([6.0, -7.0, 0.3])
    >>> bool(np.allclose(ridge.inverse(coords, ridge.forward(coords, u)), u))
    True
    """

    @classmethod
    def fit(
        cls,
        coords: Coordinates,
        mean: np.ndarray,
        cov: np.ndarray,
        bounded: np.ndarray,
        bounds: tuple[np.ndarray, np.ndarray],
    ) -> ChainedBoundRidge:
        """The map for ``bounded`` (in this order) from ``w``'s Laplace fit."""
        n = mean.size
        plain = cls(bounded, np.arange(n), bounds)
        x, slope = plain.bounded_value(coords, mean)
        beta = np.zeros((n, bounded.size))
        for k, b in enumerate(bounded):
            earlier = bounded[:k]
            given = (
                cov
                - cov[:, earlier] @ np.linalg.solve(cov[np.ix_(earlier, earlier)], cov[earlier, :])
                if k
                else cov
            )
            beta[:, k] = given[:, b] / given[b, b] / slope[k]
            beta[bounded[: k + 1], k] = 0.0
        return cls(bounded, np.arange(n), bounds, beta, (mean[bounded].copy(), x), slope)

    def forward(self, coords: Coordinates, u: Any, xp: Any = None) -> Any:
        """``w`` from the sampling coordinates ``u`` (numpy)."""
        w = np.array(u, dtype=float)
        for k in range(self.bounded.size):
            w += self.beta[:, k] * self._bend(coords, w)[0][k]
        return w

    def inverse(self, coords: Coordinates, w: np.ndarray) -> np.ndarray:
        """``u`` from ``w`` (every bend is known from ``w``)."""
        return np.asarray(w, float) - self.beta @ self._bend(coords, w)[0]

    def pull_back(self, coords: Coordinates, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``u`` from the gradient at :meth:`forward` of ``u``."""
        slopes = self._bend(coords, self.forward(coords, u))[1]
        out = np.array(grad, dtype=float)
        for k in reversed(range(self.bounded.size)):
            out[self.bounded[k]] += slopes[k] * float(self.beta[:, k] @ out)
        return out


def _near_bound_ridge(
    space: ValueSpace,
    coords: SoftBoxCoordinates,
    mean: np.ndarray,
    chol: np.ndarray,
    pivot: int,
    value_sd: np.ndarray,
) -> ChainedBoundRidge | None:
    """Partners of the soft-box parameters near one bound measured from what the box leaves.

    A soft-box parameter ``x_B`` a few sds from a bound, with partners that compensate it
    (dielectric M2: ``ln γ`` 1.2 sd above its lower bound, ``E_A`` and others following it
    given the pivot), meets a wall where ``ξ_B`` crosses the bound: ``x_B`` stops there,
    but the whitened partners keep following ``ξ_B``, and the log density falls with their
    conditional precision, not with ``1/h`` (drop > 100 at 1.5 sd along ``ln γ``'s axis).
    A :class:`ChainedBoundRidge` on those parameters (nearest its bound first) makes the
    partners follow ``x_B`` instead (regression on ``x_B`` given the pivot, which it leaves
    alone); None when no soft-box parameter lies within :data:`_SOFT_NEAR_SDS` Laplace sds
    of one bound.
    """
    from kohpymc.bound_distance import near_bounds

    v = coords.to_value(mean)[0]
    near, _ = near_bounds(space, v, value_sd, _SOFT_NEAR_SDS)
    bounded = np.flatnonzero(near & coords.soft)
    if bounded.size == 0:
        return None
    share = expit(v[bounded])
    gap = np.minimum(share, 1.0 - share) / (share * (1.0 - share) * value_sd[bounded])
    bounded = bounded[np.argsort(gap, kind="stable")]
    rest = np.array([i for i in range(mean.size) if i != pivot])
    precision = np.linalg.inv(chol @ chol.T)
    given_pivot = np.eye(mean.size)
    given_pivot[np.ix_(rest, rest)] = np.linalg.inv(precision[np.ix_(rest, rest)])
    bounds = (space.lower[bounded], space.upper[bounded])
    return ChainedBoundRidge.fit(coords, mean, given_pivot, bounded, bounds)


class _Conditional:
    """Conditional modes and Hessians of the rest given the pivot, in ``coords``."""

    def __init__(self, space: ValueSpace, coords: Coordinates, pivot: int, chol: np.ndarray):
        self.space, self.pivot = space, pivot
        self.ndim = chol.shape[0] + 1
        self.rest = np.array([i for i in range(self.ndim) if i != pivot])
        self.chol = chol
        zero, eye = np.zeros(self.ndim), np.eye(self.ndim)
        self.identity = Reparameterization("none", zero, eye, coords, "")

    def _logp(self, w_pivot: float, x: np.ndarray) -> tuple[float, np.ndarray]:
        w = np.empty(self.ndim)
        w[self.pivot], w[self.rest] = w_pivot, x
        with np.errstate(all="ignore"):
            logp, grad = self.identity.logp_dlogp(self.space, w, safe=True)
        return logp, grad[self.rest]

    def mode(
        self, w_pivot: float, start: np.ndarray, chol: np.ndarray | None = None
    ) -> tuple[np.ndarray, float]:
        """L-BFGS whitened by ``chol`` (default: the factor at the mode), with restarts.

        Restarted until it stops gaining.
        """
        chol = self.chol if chol is None else chol
        x, best = start, -np.inf
        for _ in range(4):
            result = optimize.minimize(
                self._objective(w_pivot, x, chol), np.zeros(x.size), jac=True,
                method="L-BFGS-B", options={"maxiter": 2000, "ftol": 1e-14, "gtol": 1e-8},
            )  # fmt: skip
            if not -result.fun > best + 1e-9:
                break
            x, best = x + chol @ result.x, -float(result.fun)
        return x, best

    def _objective(self, w_pivot: float, x0: np.ndarray, chol: np.ndarray):
        def objective(u):
            logp, grad = self._logp(w_pivot, x0 + chol @ u)
            if not np.isfinite(logp) or not np.all(np.isfinite(grad)):
                return np.inf, np.zeros(u.size)
            return -logp, -(chol.T @ grad)

        return objective

    def factor(
        self, w_pivot: float, x: np.ndarray, chol: np.ndarray | None = None
    ) -> np.ndarray | None:
        """Cholesky factor of the conditional Laplace covariance at ``x`` (None if not PD).

        Differenced along the axes of ``chol`` (default: the factor at the mode).
        """
        chol = self.chol if chol is None else chol
        n = x.size
        hess = _hessian(
            lambda y: self._whitened_logp(w_pivot, x, y, chol), np.zeros(n), np.full(n, 1e-3)
        )
        inner = _inverse_cholesky(hess)
        return None if inner is None else chol @ inner

    def _whitened_logp(self, w_pivot: float, x: np.ndarray, y: np.ndarray, chol: np.ndarray):
        logp, grad = self._logp(w_pivot, x + chol @ y)
        return logp, chol.T @ grad


def _march(cond: _Conditional, nodes: np.ndarray, start: float, first: np.ndarray):
    """Conditional modes, profile and Laplace factors at ``nodes``, from ``start`` outwards.

    Each optimisation starts from the linear extrapolation of the two previous modes and
    is whitened by the previous node's conditional Laplace factor: along the ridge the
    conditional scales change by orders of magnitude, and whitened by the factor at the
    mode alone the 25 optimisations took 23 600 evaluations of the log density
    (dielectric M5, 52 s of a 92 s plan).  None when a node has no finite mode or no
    positive-definite conditional Hessian.
    """
    modes = np.empty((nodes.size, first.size))
    profile = np.empty(nodes.size)
    factors = np.empty((nodes.size, first.size, first.size))
    for order in (np.flatnonzero(nodes >= start), np.flatnonzero(nodes < start)[::-1]):
        previous, chol = [(start, first)], cond.chol
        for i in order:
            guess = previous[-1][1]
            if len(previous) > 1:
                (sa, xa), (sb, xb) = previous[-2], previous[-1]
                guess = xb + (xb - xa) * (nodes[i] - sb) / (sb - sa)
            w_pivot = float(logit(nodes[i]))
            modes[i], profile[i] = cond.mode(w_pivot, guess, chol)
            if not np.isfinite(profile[i]):
                return None
            factor = cond.factor(w_pivot, modes[i], chol)
            if factor is None:
                return None
            factors[i], chol = factor, factor
            previous.append((nodes[i], modes[i]))
    return modes, profile, factors


#: a node is added between two where the splines' midpoint lies more than this far (log
#: density) below the conditional mode there (:func:`_refined`)
_MISS = 0.25

#: only between nodes whose profile lies within this of its maximum (where the draws go)
_RELEVANT = 30.0


def _refined(cond: _Conditional, nodes: np.ndarray, marched: tuple, rounds: int = 5):
    """``nodes`` and ``marched`` with nodes added where the splines miss the ridge.

    Between two nodes whose profile lies within ``_RELEVANT`` of its maximum, the
    conditional mode at the midpoint (from the splines' value there, whitened by the
    nearer node's factor) is compared with the splines' value; where the log density at
    the latter lies more than ``_MISS`` below, the midpoint becomes a node.  Repeated for
    ``rounds`` rounds, each looking only between new nodes and their neighbours.  Where the
    conditional modes turn fast (Steinhart–Hart M3: the noise and discrepancy variance
    take up the misfit below C ≈ 0, their modes moving 1.9 units between C = −1.3·10⁻⁷ and
    −7·10⁻⁸ while their conditional sds are 10⁻²–10⁻³) the spline through the default
    nodes missed it by 6–14 conditional sds, a drop of 114 at −1.5 sds along the ridge.
    """
    modes, profile, factors = marched
    fresh = np.ones(nodes.size, bool)
    for _ in range(rounds):
        curve = CubicSpline(nodes, modes, axis=0)
        added = []
        for i in range(nodes.size - 1):
            relevant = min(profile[i], profile[i + 1]) > profile.max() - _RELEVANT
            if not (relevant and (fresh[i] or fresh[i + 1])):
                continue
            s = 0.5 * (nodes[i] + nodes[i + 1])
            w_pivot = float(logit(s))
            near = factors[i] if s - nodes[i] < nodes[i + 1] - s else factors[i + 1]
            guess = curve(s)
            mode, best = cond.mode(w_pivot, guess, near)
            on_spline, _ = cond._logp(w_pivot, guess)
            if not np.isfinite(best) or not best - on_spline > _MISS:
                continue
            factor = cond.factor(w_pivot, mode, near)
            if factor is not None:
                added.append((s, mode, best, factor))
        if not added:
            break
        order = np.argsort(np.concatenate([nodes, [a[0] for a in added]]), kind="stable")
        nodes = np.concatenate([nodes, [a[0] for a in added]])[order]
        modes = np.concatenate([modes, [a[1] for a in added]])[order]
        profile = np.concatenate([profile, [a[2] for a in added]])[order]
        factors = np.concatenate([factors, [a[3] for a in added]])[order]
        fresh = np.concatenate([np.zeros(fresh.size, bool), np.ones(len(added), bool)])[order]
    return nodes, (modes, profile, factors)


def _pivot_weights(nodes: np.ndarray, profile: np.ndarray, n: int = 6401, *, in_w: bool = False):
    """Grid over ``w_p`` and the normalised weights of ``exp(profile)`` (logistic tails outside).

    ``profile`` is interpolated in ``s`` at the nodes, or with ``in_w`` in ``w_p = logit(s)``,
    where its logistic tails near the faces are straight (in ``s`` they are ``ln(1 − s)``,
    which a cubic between the last two nodes, ``s = 0.9957`` and ``1 − 10⁻⁶``, misses).
    """
    w = np.linspace(-16.0, 16.0, n)
    lo, hi = logit(nodes[0]), logit(nodes[-1])
    if in_w:
        logp = CubicSpline(logit(nodes), profile)(np.clip(w, lo, hi))
    else:
        logp = CubicSpline(nodes, profile)(np.clip(expit(w), nodes[0], nodes[-1]))
    logp = logp + np.minimum(w - lo, 0.0) - np.maximum(w - hi, 0.0)
    weight = np.exp(logp - logp.max())
    return w, weight / weight.sum()


def _pivot_moments(nodes: np.ndarray, profile: np.ndarray) -> tuple[float, float]:
    """Mean and sd of ``w_p`` under ``exp(profile)`` by quadrature (logistic tails outside)."""
    w, weight = _pivot_weights(nodes, profile)
    mean = float(weight @ w)
    return mean, float(np.sqrt(weight @ (w - mean) ** 2))


#: drop of the log density at ±1.5 along the pivot's axis, off a Gaussian's by more than
#: this, that has the pivot warped to normal quantiles (:func:`_pivot_warp`)
_WARP_ERROR = 1.0


def _pivot_warp(nodes: np.ndarray, marginal: np.ndarray) -> CubicSpline | None:
    """``t → w_p`` matching the quantiles of ``exp(marginal)`` to a standard normal's.

    ``marginal`` is the pivot's Laplace marginal at ``nodes`` (the profile plus the log
    determinant of the conditional factor).  A one-sided ridge (a parameter the data bound
    on one side only: a substrate-inhibition constant ``K_i`` whose effect grows as
    ``1/K_i``) has a marginal with a double-exponential wall on one side and a plateau
    ending in the box on the other, which no affine ``t`` makes Gaussian.  None when the
    grid does not resolve the marginal or the spline is not increasing.
    """
    w, weight = _pivot_weights(nodes, marginal, n=32001, in_w=True)
    if np.count_nonzero(weight > 1e-12 * weight.max()) < 200:
        return None
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (weight[1:] + weight[:-1]))])
    cdf /= cdf[-1]
    keep = np.concatenate([[True], np.diff(cdf) > 0])  # strictly increasing for np.interp
    return spline_through_quantiles(cdf[keep], w[keep])


def ridge_curve_plan(
    space: ValueSpace,
    laplace: Reparameterization,
    mode: Mode,
    *,
    n_nodes: int = 25,
    own: bool = False,
    min_ratio: float = _RIDGE_RATIO,
) -> RidgeCurvePlan | None:
    """A :class:`RidgeCurvePlan` from a log-logit Laplace plan, or None without a long ridge.

    Parameters
    ----------
    space : ValueSpace
    laplace : Reparameterization
        The whitened plan in log-logit coordinates (no walls, no bound ridge); with
        ``own``, in PyMC's coordinates.
    mode : Mode
    n_nodes : int
        Nodes of the splines from face to face.
    own : bool
        Lead the ridge by an interval parameter in its own units (its position between its
        bounds, PyMC's logit), the members staying in PyMC's coordinates: for a ridge of
        parameters whose boxes do not lie on the positive axis (Steinhart–Hart's
        ``C ∈ (−5·10⁻⁷, 5·10⁻⁷)``), which have no log scale.
    min_ratio : float
        The pivot's marginal over conditional Laplace sd above which its ridge is
        followed (log-logit pivots only; ``own`` uses ``_RIDGE_RATIO``).

    Examples
    --------
    >>> curve = ridge_curve_plan(space, laplace, mode)  # doctest: +SKIP
    >>> curve.kind  # doctest: +SKIP
    'ridge-curve-soft-box'
    """
    value_sd = laplace.value_sd
    candidates = space.bounded_intervals() if own else None
    found = _ridge_members(laplace, candidates, min_ratio) if value_sd is not None else None
    if found is None or value_sd is None:
        return None
    pivot, members = found
    coords = _soft_box(space, laplace, members, own=own)
    if coords is None:
        return None
    mean, chol = _laplace(space, coords, coords.from_value(mode.value))
    if chol is None:
        return None
    ridge = _near_bound_ridge(space, coords, mean, chol, pivot, value_sd)
    if ridge is not None:
        coords = coords.with_ridge(ridge)
        mean, chol = _laplace(space, coords, coords.from_value(mode.value))
        if chol is None:
            return None
    rest = np.array([i for i in range(space.ndim) if i != pivot])
    precision = np.linalg.inv(chol @ chol.T)
    conditional = _inverse_cholesky(precision[np.ix_(rest, rest)])
    if conditional is None:
        return None
    cond = _Conditional(space, coords, pivot, conditional)
    nodes = _nodes(n_nodes)
    marched = _march(cond, nodes, float(expit(mean[pivot])), mean[rest].copy())
    if marched is None:
        return None
    if own:
        nodes, marched = _refined(cond, nodes, marched)
    modes, profile, factors = marched
    lower = np.tril_indices(rest.size, -1)
    entries = [np.concatenate([np.log(np.diag(f)), f[lower]]) for f in factors]
    centre, scale = _pivot_moments(nodes, profile)
    kind = "ridge-curve-own-units-soft-box" if own else "ridge-curve-soft-box"
    plan = RidgeCurvePlan(
        kind, np.zeros(space.ndim), np.eye(space.ndim), coords, "", mode,
        pivot=pivot, rest=rest, centre=centre, scale=scale, nodes=nodes,
        curve=CubicSpline(nodes, modes, axis=0),
        factor=CubicSpline(nodes, np.array(entries), axis=0),
    )  # fmt: skip
    plan = replace(plan, gaussian_score=_gaussian_score(space, plan))
    # own units too: Steinhart–Hart under M4 (GP discrepancy) has its pivot C end in a wall
    # where the GP must take up the physics' misfit (log density 20 down at −2 along the
    # affine pivot, 2 for a Gaussian); warped, its axis drops 2.0 and 8.0 at ±2 and ±4
    # (see the module docstring)
    if not _axis_errors(space, plan)[:2].max() > _WARP_ERROR:
        return plan
    volume = np.array([np.log(np.diag(f)).sum() for f in factors])
    warp = _pivot_warp(nodes, profile + volume)
    if warp is None:
        return plan
    warped = replace(plan, kind=f"{kind}-warped", warp=warp)
    warped = replace(warped, gaussian_score=_gaussian_score(space, warped))
    return warped if warped.gaussian_score < plan.gaussian_score else plan
