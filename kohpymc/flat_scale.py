r"""Bounded parameters sampled on the scale on which their prior is flat, in a soft box.

Physics written in a parameter's natural units is often linear in it, or in its log:
Norton creep, ``log ε̇ = log A + n log σ − Q/(R T ln 10)``, is linear in
``(ln A, n, Q)``, and with ``A ~ LogUniform`` and ``n, Q ~ Uniform`` the posterior is a
Gaussian ridge (correlation 0.999) in exactly those units.  PyMC samples each of them as
the logit of its position in its box, ``v = ln(x − a) − ln(b − x)``, which is nearly
linear near the middle of the box but not exactly: over ±3 posterior sds the slope
``dv/d ln A`` changes by 20 % and ``dv/dQ`` by 1–2 %, and across a ridge 25 times
narrower than long that bends the ridge by several of its widths (creep, M0: the
log density drops 11.4 at +3 Laplace sds along the whitened ``A`` axis, 4.5 for a
Gaussian; 16–23 divergences in 4 × 1000 draws, starting beyond 3 sds).  The
log-logit coordinates (:func:`kohpymc.reparameterization.log_coordinates`) take the
log of ``n`` and ``Q`` as well, which bends the ridge again.

:class:`SoftFlatScaleCoordinates` samples every bounded parameter on the scale ``ℓ`` on
which its prior is flat (``ln x`` for a log-uniform prior, ``x`` for a uniform one:
:func:`flat_scale_masks`), through a soft box,

.. math:: ℓ = ℓ_a + h\,[\mathrm{softplus}((ξ − ℓ_a)/h) − \mathrm{softplus}((ξ − ℓ_b)/h)],

so ``ℓ ≈ ξ`` more than a few ``h`` inside the bounds (a ridge straight in ``ℓ`` stays
straight in ``ξ``), and beyond a bound the density decays like ``e^{−|ξ − ℓ_b|/h}``: no
wall, no hole of zero density.  ``h`` is :data:`SOFT_WIDTH` Laplace sds.  The map is
written once over :class:`~kohpymc.reparameterization.ArrayMath`, so it also runs on
nutpie's native path.  :func:`flat_scale_plans` offers it to
:func:`kohpymc.reparameterization.plan`, which takes it over the best Laplace map where
it fits as well at ±1.5 sds and clearly better at ±3 (creep M0: mean error of the axes'
drops at ±3 sds 1.50 in PyMC's coordinates, 0.35 here, the rest from the noise sd's skew;
16–23 divergences in 4 × 1000 draws → 0 at three seeds).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
from scipy.special import expit

from kohpymc.reparameterization import (
    NUMPY,
    ArrayMath,
    BoundRidge,
    Coordinates,
    Mode,
    Reparameterization,
    VarianceShare,
    _whitened,
    prior_scales,
)
from kohpymc.value_space import ValueSpace

__all__ = [
    "SHEAR_SDS",
    "SOFT_WIDTH",
    "SoftBoxShear",
    "SoftFlatScaleCoordinates",
    "flat_scale_masks",
    "flat_scale_plans",
]

#: soft-box width ``h`` in Laplace sds of the flat-scale coordinate: the map's slope is
#: ``1 − e^{−d/h}`` at ``d`` inside a bound (creep's ``A``, bounds 5.7 sds from the mode:
#: 0.9998 at 3 sds, 0.99 at 4.5)
SOFT_WIDTH = 0.25

#: a soft element with a bound within this many Laplace sds of the mode has its partners
#: follow what the box leaves of it (:class:`SoftBoxShear`); further out NUTS never goes
SHEAR_SDS = 8.0


def _softplus(t: Any, xp: ArrayMath) -> Any:
    return xp.logaddexp(0.0, t)


def flat_scale_masks(space: ValueSpace, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Interval elements whose prior is flat on the log scale, and those flat in own units.

    A positive interval element goes on the log scale when the median of its prior
    draws lies closer to the middle of ``(ln a, ln b)`` than to the middle of ``(a, b)``
    (a log-uniform prior: ``√(ab)``; a uniform one: ``(a + b)/2``); every other interval
    element with finite bounds stays in its own units.

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.priors import LogUniform, Uniform
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     a = LogUniform(1e-9, 1e-3).create("a")
    ...     e = Uniform(1e4, 6e4).create("e")
    >>> log, own = flat_scale_masks(value_space(model), seed=1)
    >>> log.tolist(), own.tolist()
    ([True, False], [False, True])
    """
    interval = space.bounded_intervals()
    if not interval.any():
        return interval, interval
    median_v, _ = prior_scales(space, seed)
    a, b = space.lower, space.upper
    with np.errstate(all="ignore"):
        median = a + (b - a) * expit(median_v)
        linear = np.abs((median - a) / (b - a) - 0.5)
        logarithmic = np.abs(np.log(median / a) / np.log(b / a) - 0.5)
    log_scale = interval & (a > 0) & (logarithmic < linear)
    return log_scale, interval & ~log_scale


@dataclass(frozen=True)
class SoftFlatScaleCoordinates(Coordinates):
    r"""Interval elements on their prior's flat scale, in a soft box (module docstring).

    ``log_scale`` elements have ``ℓ = ln x``, ``own`` elements ``ℓ = x``; ``width`` is
    ``h`` per element, in units of ``ℓ``.  Every other element has ``w = v``.  Unlike
    the base class, ``log_scale`` elements are not log-logit: ``walls`` is unused.

    Examples
    --------
    >>> coords = SoftFlatScaleCoordinates(
    ...     np.array([True, False]), np.array([1e-11, 1.5e5]), np.array([1e-8, 4.5e5]),
    ...     own=np.array([False, True]), width=np.array([0.1, 1e3]))
    >>> w = np.array([np.log(3e-10), 2.9e5])  # far inside: x = exp(w_0), w_1
    >>> v = coords.to_value(w)[0]
    >>> x = coords.lower + (coords.upper - coords.lower) / (1 + np.exp(-v))
    >>> bool(np.allclose(x, [3e-10, 2.9e5]))
    True
    >>> bool(np.allclose(coords.from_value(v), w))
    True
    """

    own: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    width: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def name(self) -> str:
        """``"soft-flat-scale"``."""
        return "soft-flat-scale"

    def map_constants(self) -> np.ndarray:
        """``h`` of every element, then the shear's ``β`` (row-major) if there is one."""
        beta = self.ridge.beta if isinstance(self.ridge, SoftBoxShear) else np.zeros(0)
        return np.concatenate([np.ravel(self.width), np.ravel(beta)]).astype(float)

    def with_map_constants(self, values: Any) -> SoftFlatScaleCoordinates:
        """The coordinates with ``h`` and the shear's ``β`` read from ``values``.

        Examples
        --------
        >>> coords = SoftFlatScaleCoordinates(np.array([True]), np.array([1.0]),
        ...     np.array([10.0]), own=np.array([False]), width=np.array([0.1]))
        >>> coords.with_map_constants(np.array([0.2])).width.tolist()
        [0.2]
        """
        n = self.width.size
        ridge = self.ridge
        if isinstance(ridge, SoftBoxShear):
            ridge = replace(ridge, beta=values[n:].reshape(ridge.beta.shape))
        return replace(self, width=values[:n], ridge=ridge)

    def scale_text(self, labels: Any) -> str:
        """Which parameters are on the log scale and which in their own units."""
        logs = ", ".join(labels.get(int(i), str(i)) for i in np.flatnonzero(self.log_scale))
        own = ", ".join(labels.get(int(i), str(i)) for i in np.flatnonzero(self.own))
        parts = [f"{logs} on the log scale" if logs else "", f"{own} in own units" if own else ""]
        return (
            "; bounded parameters on the scale of their flat prior ("
            + ", ".join(p for p in parts if p)
            + "), in a soft box, where a ridge straight in those units stays straight"
        )

    def soft_value(self, xi: Any, index: Any, xp: ArrayMath = NUMPY) -> Any:
        """``ℓ(ξ)`` of the soft elements ``index`` (over ``xp``)."""
        lo, hi = (bound[index] for bound in self.flat_bounds())
        h = self.width[index]
        p, c = (xi - lo) / h, (hi - lo) / h
        return lo + h * (_softplus(p, xp) - _softplus(p - c, xp))

    def soft_slope(self, xi: np.ndarray, index: np.ndarray) -> np.ndarray:
        """``dℓ/dξ = expit(p)·expit(c − p)·(1 − e^{−c})`` of the soft elements ``index``."""
        lo, hi = (bound[index] for bound in self.flat_bounds())
        h = self.width[index]
        p, c = (xi - lo) / h, (hi - lo) / h
        return expit(p) * expit(c - p) * -np.expm1(-c)

    def _groups(self) -> list[tuple[np.ndarray, bool]]:
        """``(indices, on the log scale)`` of the two groups of soft elements."""
        groups = [(np.flatnonzero(self.log_scale), True), (np.flatnonzero(self.own), False)]
        return [(index, log) for index, log in groups if index.size]

    def flat_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounds of every element on its flat scale (``ln a`` or ``a``; NaN if none)."""
        with np.errstate(all="ignore"):
            lo = np.where(self.log_scale, np.log(self.lower), self.lower)
            hi = np.where(self.log_scale, np.log(self.upper), self.upper)
        return lo, hi

    def _parts(self, xi: Any, index: np.ndarray, log: bool, xp: ArrayMath):
        """``v``, the log-Jacobian per element, and ``(ℓ, ln(x − a), ln(b − x), p, c)``."""
        a, b, h = self.lower[index], self.upper[index], self.width[index]
        lo, hi = (bound[index] for bound in self.flat_bounds())
        c = (hi - lo) / h
        p = (xi - lo) / h
        above = _softplus(p, xp) - _softplus(p - c, xp)  # (ℓ − ℓ_a)/h
        below = _softplus(c - p, xp) - _softplus(-p, xp)  # (ℓ_b − ℓ)/h
        ell = lo + h * above
        if log:  # x − a = a (e^{ℓ − ℓ_a} − 1), b − x = b (1 − e^{−(ℓ_b − ℓ)})
            log_above = np.log(a) + xp.log(xp.expm1(h * above))
            log_below = np.log(b) + xp.log(-xp.expm1(-h * below))
        else:
            log_above, log_below = xp.log(h * above), xp.log(h * below)
        # log dv/dℓ (+ ℓ on the log scale, dx/dℓ = x) + log dℓ/dξ
        logjac = np.log(b - a) - log_above - log_below - _softplus(-p, xp) - _softplus(p - c, xp)
        logjac = logjac + xp.log(-xp.expm1(-c)) + (ell if log else 0.0)
        return log_above - log_below, logjac, (ell, log_above, log_below, p, c)

    def to_value(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``v(w)``, ``dv/dw``, ``d log|dv/dw| / dw`` and ``Σ log|dv/dw|``."""
        w = np.asarray(w, float)
        v, dv, dlogjac = w.copy(), np.ones_like(w), np.zeros_like(w)
        total = 0.0
        with np.errstate(all="ignore"):
            for index, log in self._groups():
                v_m, logjac, (ell, log_above, log_below, p, c) = self._parts(
                    w[index], index, log, NUMPY
                )
                # dℓ/dξ = expit(p) expit(c − p) (1 − e^{−c})
                slope = np.exp(-np.logaddexp(0.0, -p) - np.logaddexp(0.0, p - c)) * -np.expm1(-c)
                # d/dℓ of log dv/dℓ: −1/(x − a) + 1/(b − x), times x and plus 1 for ℓ = ln x
                shift = ell if log else 0.0
                d_ell = np.exp(shift - log_below) - np.exp(shift - log_above) + float(log)
                h = self.width[index]
                v[index], dv[index] = v_m, np.exp(logjac)
                dlogjac[index] = slope * d_ell + (expit(-p) - expit(p - c)) / h
                total += float(np.sum(logjac))
        return v, dv, dlogjac, total

    def value_and_log_jacobian(self, w: Any, xp: ArrayMath = NUMPY) -> tuple[Any, Any]:
        """``v(w)`` and ``Σ log|dv/dw|`` of the elementwise map, over ``xp``."""
        out, total = xp.copy(w), 0.0
        for index, log in self._groups():
            v_m, logjac, _ = self._parts(w[index], index, log, xp)
            out = xp.put(out, index, v_m)
            total = total + xp.sum(logjac)
        return out, total

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """``w(v)``: the soft boxes inverted, then the variance shares and the ridge."""
        v = np.asarray(v, float)
        w = v.copy()
        for index, log in self._groups():
            a, b, h = self.lower[index], self.upper[index], self.width[index]
            lo, hi = (bound[index] for bound in self.flat_bounds())
            c = (hi - lo) / h
            share = expit(v[index])
            gap = np.log1p((b - a) / a * share) if log else (b - a) * share
            g = np.clip(gap / h, 1e-300, c * (1 - 1e-15))
            # log(expm1(g)) as g + log(1 - e^-g): no overflow where g > 709 (a narrow tail)
            w[index] = lo + h * (g + np.log(-np.expm1(-g)) - np.log(-np.expm1(g - c)))
        w = w if self.shares is None else self.shares.inverse(w)
        return w if self.ridge is None else self.ridge.inverse(self, w)


@dataclass(frozen=True)
class SoftBoxShear(BoundRidge):
    r"""The other coordinates follow what the soft box leaves of the elements near a bound.

    Beyond a bound ``ℓ`` stops while ``ξ`` runs on; a partner that the whitening moves
    with ``ξ`` along a ridge then leaves the ridge, whose width is a small fraction of its
    length, so the log density falls with the partner's conditional precision: a kink
    NUTS diverges on (creep, M0: ``A``'s bounds 5.7 Laplace sds from the mode, one
    divergence in 4 × 1000 draws starting there).  With the elements ``b_0, b_1, …``
    (``bounded``, nearest its bound first), step ``k`` adds
    ``beta[:, k]·(ℓ(w_{b_k}) − w_{b_k})`` to ``w``, ``beta[:, k]`` the regression on
    ``ξ_{b_k}`` given ``b_0 … b_{k−1}`` (zero on ``b_0 … b_k``): inside the box the bend is
    zero and the map the identity; beyond a bound the partners follow ``ℓ``.  The map is
    unit-triangular (no Jacobian term), its inverse explicit, and it is written over
    :class:`~kohpymc.reparameterization.ArrayMath`.  ``others`` is every index.

    Examples
    --------
    >>> coords = SoftFlatScaleCoordinates(np.array([False, False]), np.array([0.0, -9.0]),
    ...     np.array([1.0, 9.0]), own=np.array([True, False]), width=np.array([0.01, 1.0]))
    >>> cov = np.array([[1.0, 0.9], [0.9, 1.0]])
    >>> shear = SoftBoxShear.fit(coords, np.array([0.5, 0.0]), cov, np.array([0]))
    >>> u = np.array([1.3, 0.2])  # beyond the upper bound 1: the partner follows ℓ ≈ 1
    >>> w = shear.forward(coords, u)
    >>> bool(np.allclose(w, [1.3, 0.2 - 0.9 * 0.3], atol=1e-6))
    True
    >>> bool(np.allclose(shear.inverse(coords, w), u))
    True
    """

    prefix: ClassVar[str] = ""

    def text(self, named: str) -> str:
        """The part of a plan's reason that says what the map does."""
        return f"; the others following what the box leaves of {named} beyond its bounds"

    @classmethod
    def fit(  # type: ignore[override]
        cls,
        coords: Coordinates,
        mean: np.ndarray,
        cov: np.ndarray,
        bounded: np.ndarray,
        bounds: Any = None,
    ) -> SoftBoxShear:
        """The map for ``bounded`` (in this order) from the Laplace covariance ``cov`` of ``ξ``."""
        n = mean.size
        beta = np.zeros((n, bounded.size))
        for k, b in enumerate(bounded):
            earlier = bounded[:k]
            given = cov
            if k:
                given = cov - cov[:, earlier] @ np.linalg.solve(
                    cov[np.ix_(earlier, earlier)], cov[earlier, :]
                )
            beta[:, k] = given[:, b] / given[b, b]
            beta[bounded[: k + 1], k] = 0.0
        bounds = (coords.lower[bounded], coords.upper[bounded])
        return cls(bounded, np.arange(n), bounds, beta)

    def _bend(self, coords: Any, w: Any, k: int, xp: ArrayMath = NUMPY) -> Any:  # type: ignore[override]
        """``ℓ(w_{b_k}) − w_{b_k}``."""
        b = int(self.bounded[k])
        return coords.soft_value(w[b], b, xp) - w[b]

    def forward(self, coords: Any, u: Any, xp: ArrayMath = NUMPY) -> Any:
        """``w`` from the sampling coordinates ``u`` (over ``xp``)."""
        w = xp.copy(u)
        for k in range(self.bounded.size):
            w = xp.add(w, self.others, self.beta[:, k] * self._bend(coords, w, k, xp))
        return w

    def inverse(self, coords: Any, w: np.ndarray) -> np.ndarray:
        """``u`` from ``w`` (each ``w_{b_k}`` is final from step ``k`` on)."""
        w = np.asarray(w, float)
        bends = np.array([self._bend(coords, w, k) for k in range(self.bounded.size)])
        return w - self.beta @ bends

    def pull_back(self, coords: Any, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``u`` from the gradient at :meth:`forward` of ``u``."""
        w = self.forward(coords, np.asarray(u, float))
        out = np.array(grad, dtype=float)
        for k in reversed(range(self.bounded.size)):
            b = int(self.bounded[k])
            slope = coords.soft_slope(w[b], b) - 1.0
            out[b] += slope * float(self.beta[:, k] @ out)
        return out


def _near_bounds(coords: SoftFlatScaleCoordinates, plan: Reparameterization) -> np.ndarray:
    """Soft elements with a bound within :data:`SHEAR_SDS` Laplace sds, nearest first."""
    index = np.flatnonzero(coords.log_scale | coords.own)
    sd = np.sqrt(np.einsum("ij,ij->i", plan.chol, plan.chol))[index]
    lo, hi = (bound[index] for bound in coords.flat_bounds())
    centre = plan.mean[index]
    with np.errstate(all="ignore"):
        gap = np.minimum(centre - lo, hi - centre) / sd
    near = np.isfinite(gap) & (gap < SHEAR_SDS)
    return index[near][np.argsort(gap[near], kind="stable")]


def _widths(
    space: ValueSpace, laplace: Reparameterization, log: np.ndarray, own: np.ndarray
) -> np.ndarray | None:
    """``h``: :data:`SOFT_WIDTH` Laplace sds of each soft element's flat-scale coordinate.

    From ``laplace``'s value-space sds at the mode, carried by ``dℓ/dv``; None when one
    is not finite and positive.
    """
    if laplace.value_sd is None or laplace.mode is None:
        return None
    a, b = space.lower, space.upper
    with np.errstate(all="ignore"):
        share = expit(laplace.mode.value)
        x = a + (b - a) * share
        dx_dv = (b - a) * share * (1.0 - share)
        d_ell = np.where(log, dx_dv / x, dx_dv)
        width = np.where(log | own, SOFT_WIDTH * d_ell * laplace.value_sd, 1.0)
    soft = log | own
    if not np.all(np.isfinite(width[soft]) & (width[soft] > 0)):
        return None
    return width


def flat_scale_plans(
    space: ValueSpace,
    plans: list[Reparameterization],
    mode: Mode,
    seed: int,
    shares: VarianceShare | None = None,
) -> list[Reparameterization]:
    """The whitened plan in :class:`SoftFlatScaleCoordinates`, as a one-element list.

    The widths come from the first of ``plans`` (PyMC's coordinates); empty without
    interval parameters, without a plan, or without a positive-definite Hessian.

    Examples
    --------
    >>> found = flat_scale_plans(space, plans, mode, seed=1)  # doctest: +SKIP
    >>> found[0].kind  # doctest: +SKIP
    'flat-scale-affine'
    """
    if not plans:
        return []
    log, own = flat_scale_masks(space, seed)
    if not (log | own).any():
        return []
    width = _widths(space, plans[0], log, own)
    if width is None:
        return []
    coords = SoftFlatScaleCoordinates(
        log, space.lower.copy(), space.upper.copy(), shares=shares, own=own, width=width
    )
    start = coords.from_value(mode.value)
    if not np.all(np.isfinite(start)):
        return []
    found = _whitened(space, coords, mode.value, mode)
    if found is None:
        return []
    bounded = _near_bounds(coords, found)
    if bounded.size == 0:
        return [found]
    shear = SoftBoxShear.fit(coords, found.mean, found.chol @ found.chol.T, bounded)
    sheared = _whitened(space, coords.with_ridge(shear), mode.value, mode)
    return [found if sheared is None else sheared]
