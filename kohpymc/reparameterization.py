r"""Sampling coordinates fitted to the posterior: the mode, its Laplace covariance, a whitening map.

Physics parameters come in natural units (a modulus of 2·10¹¹ Pa next to a length of
10⁻³ m), nearly collinear, or confounded multiplicatively (only ``k·c`` is informed).
NUTS adapts a diagonal mass matrix, so a posterior whose correlation is 0.9999 or whose
ridge is 10⁴ times longer than wide costs it thousands of leapfrog steps per draw.
Before sampling, :func:`plan` therefore

1. finds the posterior mode in PyMC's unconstrained value space ``v`` by L-BFGS from
   several starts: PyMC's initial point, the caller's starts (e.g. a least-squares fit),
   and a scrambled Sobol design over the central 90 % of the prior;
2. offers two elementwise coordinate systems ``w → v``: PyMC's own (``w = v``), and
   one where every interval prior ``Uniform(a, b)`` with ``a > 0`` is sampled on the
   log scale, ``w = logit((ln x − ln a) / (ln b − ln a))`` — a multiplicative ridge
   (``x₁^p x₂^q`` fixed) is straight there and curved in ``logit((x − a)/(b − a))``;
3. in each, computes the Hessian ``H`` of ``−log p`` at the mode by central differences
   of the gradient (a second pass in the coordinates whitened by the first corrects
   the step sizes), and scores how Gaussian the posterior is there: the drop of
   ``log p`` at ±1.5 standard deviations along each principal axis, which is 1.125 for
   a Gaussian;
4. when the mode lies against a prior bound (:func:`kohpymc.prior_bounds.hits_at_mode`),
   also scores each system with a :class:`BoundRidge`: a partner that compensates the
   bounded parameter linearly in its own units follows it along a ridge that the
   interval transform bends exponentially near the bound; the map measures the
   partner from that regression, which straightens the ridge (dielectric M0: score 27
   → 0.74, 58 → 10–12 leapfrog steps per draw);
5. keeps the best-scoring system and samples ``z`` with ``w = μ + L z``
   (``L Lᵀ = H⁻¹``), so the sampler sees a posterior close to a standard normal;
6. where every Laplace map fits badly (score > 1), also tries a straight ridge cut by
   the prior box (:class:`BoxRidgePlan`) and a curved one followed from face to face
   (:class:`kohpymc.ridge_curve.RidgeCurvePlan`, led by a parameter on the log scale, or
   in its own units when no interval prior lies on the positive axis); and, where the
   best fits badly on average or along one axis, a long straight ridge that a face cuts
   off (:class:`kohpymc.ridge_segment.SegmentPlan`, bounded parameters on the scale of
   their flat prior, declined where the ridge curves away from its line); each is kept
   when it scores better, a plan whose density has zero-density holes near the mode
   ranking last;
7. where no map along a ridge competes, also fits the Laplace map with every bounded
   parameter on the scale on which its prior is flat (``ln x`` for a log-uniform prior,
   ``x`` for a uniform one) in a soft box (:mod:`kohpymc.flat_scale`), and keeps it when
   it fits as well at ±1.5 sds and its drops at ±3 sds are at least twice as close to a
   Gaussian's: a ridge straight in those units, which the interval transforms bend a few
   sds out (creep, ``ln A`` against ``Q``: drop 11.4 at +3 sds, 4.5 for a Gaussian).

Draws map back through ``z → w → v → parameters``; the InferenceData holds the user's
parameters only.  The density in ``z`` is exact (the log-Jacobian of the elementwise
map is added; the affine map's is constant), so the reparameterisation changes the
geometry the sampler sees, never the posterior.  When the Hessian is not positive
definite at the best mode the plan is ``"none"`` with the reason, and sampling runs in
PyMC's coordinates from the mode.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
from scipy import optimize, stats
from scipy.special import expit

from kohpymc.prior_bounds import MODE_SDS, hits_at_mode, interval_labels
from kohpymc.value_space import ValueSpace, transformed_value

__all__ = [
    "NUMPY",
    "ArrayMath",
    "BoundRidge",
    "Coordinates",
    "Mode",
    "Reparameterization",
    "VarianceShare",
    "find_mode",
    "plan",
]

#: log-density drop at ±1.5 sd along a principal axis of a Gaussian
_GAUSSIAN_DROP = 0.5 * 1.5**2

#: Gaussian score below which a flat ridge ending on the prior box is sampled along its
#: segment (where the Laplace maps fit badly, scores 20–35 on ``y = k c x`` in prior boxes,
#: it is whenever it scores better); a flat ridge sampled along its length scores about
#: 0.3–0.5 (a logistic in ``t``)
_BOX_RIDGE_SCORE = 1.0


#: Gaussian score above which a whitened plan is tried with a quadratic bend (a parabolic
#: ridge: dielectric M0's ε_∞–E_A axis drops 4.9 at ±1.5 sd, 1.125 for a Gaussian)
_BEND_SCORE = 0.25

#: marginal over conditional Laplace sd of a ridge's pivot above which a ridge that no
#: Laplace map fits (score above ``_BOX_RIDGE_SCORE``) is followed when no longer ridge
#: (ratio above :data:`kohpymc.ridge_curve._RIDGE_RATIO`) is found
_ONE_SIDED_RATIO = 2.0

#: Gaussian score above which a plan that no parabola improves has its worst axes followed
#: along the others' conditional modes (:func:`kohpymc.bends.follow_plan`)
_FOLLOW_SCORE = 5.0
#: a bound this many Laplace sds from the mode may end the ridge of a plan that fits badly
#: (the outer node of the path :func:`kohpymc.bends.follow_plan` follows)
_FAR_BOUND_SDS = 4.5
#: eigenvalues of the unit-diagonal Hessian below this share of the largest are raised to
#: it for a provisional whitening, whose axes are then differenced again (:func:`_laplace`)
_PROVISIONAL_FLOOR = 1e-9
#: L-BFGS options of the mode refinement in whitened coordinates (tight: along a narrow
#: ridge the default stopping rule leaves the mode several log-density units short)
_WHITENED_REFINE = {"maxiter": 5000, "ftol": 1e-15, "gtol": 1e-10}


def _np_put(out: np.ndarray, index: Any, value: Any) -> np.ndarray:
    out[index] = value
    return out


def _np_add(out: np.ndarray, index: Any, value: Any) -> np.ndarray:
    out[index] += value
    return out


@dataclass(frozen=True)
class ArrayMath:
    """The array operations the coordinate maps use, for numpy or PyTensor.

    The maps ``z → v`` are written once over this namespace: :data:`NUMPY` evaluates
    them (the Python log density), ``kohpymc.native.PYTENSOR`` builds them as a graph
    (the native one).  ``copy`` returns an array the ``put``/``add`` updates may modify
    (in place for numpy, a new variable for PyTensor); ``where`` is elementwise.

    Examples
    --------
    >>> NUMPY.put(NUMPY.copy(np.zeros(2)), 1, 3.0)
    array([0., 3.])
    """

    exp: Any
    expm1: Any
    log: Any
    expit: Any
    logaddexp: Any
    dot: Any
    where: Any
    all: Any
    sum: Any
    copy: Any
    put: Any
    add: Any


#: :class:`ArrayMath` of numpy (and scipy's ``expit``)
NUMPY = ArrayMath(
    np.exp, np.expm1, np.log, expit, np.logaddexp, np.dot, np.where, np.all, np.sum,
    lambda x: np.array(x, dtype=float), _np_put, _np_add,
)  # fmt: skip


def _log_logit(w: Any, a: np.ndarray, b: np.ndarray, xp: ArrayMath = NUMPY):
    """``v = logit((x − a)/(b − a))`` of ``x = a (b/a)^expit(w)``, and ``g = dv/dw``.

    Also returns ``(s, x, x − a, b − x, ln(b/a), ds/dw)`` for the derivatives.
    """
    la, lb = np.log(a), np.log(b)
    c = lb - la
    s = xp.expit(w)
    x = xp.exp(la + c * s)
    above = a * xp.expm1(c * s)  # x - a, without cancellation
    below = -b * xp.expm1(-c * (1.0 - s))  # b - x
    ds = s * (1.0 - s)
    g = (b - a) / (above * below) * x * c * ds
    return xp.log(above) - xp.log(below), g, (s, x, above, below, c, ds)


def _log_walls(w: Any, a: np.ndarray, b: np.ndarray, xp: ArrayMath = NUMPY):
    """``v = ln(x − a) − ln(b − x)`` of ``x = e^w``, ``g = dv/dw``, and ``(x, x − a, b − x)``."""
    x = xp.exp(w)
    above, below = x - a, b - x
    g = x * (b - a) / (above * below)
    return xp.log(above) - xp.log(below), g, (x, above, below)


@dataclass(frozen=True)
class Coordinates:
    """Elementwise map from sampling coordinates ``w`` to PyMC's value space ``v``.

    ``log_scale[i]`` marks interval elements ``Uniform(a, b)``, ``a > 0``, sampled as
    ``w = logit((ln x − ln a)/(ln b − ln a))`` or, with ``walls=True``, as ``w = ln x``
    with zero density outside ``(ln a, ln b)`` (used only when the posterior lies
    many standard deviations inside the bounds, where the walls are never met and
    a ridge ``x₁^p x₂^q = const`` stays exactly straight); all other elements have
    ``w = v``.  ``ridge`` and ``shares`` act before the elementwise map.
    """

    log_scale: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    walls: bool = False
    shares: VarianceShare | None = None
    ridge: BoundRidge | None = None

    @classmethod
    def identity(cls, ndim: int) -> Coordinates:
        """PyMC's own coordinates."""
        return cls(np.zeros(ndim, bool), np.full(ndim, np.nan), np.full(ndim, np.nan))

    def with_shares(self, shares: VarianceShare | None) -> Coordinates:
        """The same elementwise map preceded by the variance-share map ``shares``."""
        return replace(self, shares=shares)

    def with_ridge(self, ridge: BoundRidge | None) -> Coordinates:
        """The same maps preceded by the bound-ridge map ``ridge``."""
        return replace(self, ridge=ridge)

    def elementwise(self) -> Coordinates:
        """The elementwise maps alone (without the shares and the ridge)."""
        return replace(self, shares=None, ridge=None)

    @property
    def name(self) -> str:
        """``"value"`` (PyMC's coordinates), ``"log-logit"`` or ``"log"``, with a prefix."""
        name = "value" if not self.log_scale.any() else "log" if self.walls else "log-logit"
        return name if self.ridge is None else f"bound-ridge-{name}"

    def map_constants(self) -> np.ndarray:
        """Numbers of the map fitted to the posterior, flattened (none: the priors' bounds).

        See :meth:`Reparameterization.map_constants`.
        """
        return np.zeros(0)

    def with_map_constants(self, values: Any) -> Coordinates:
        """The coordinates with :meth:`map_constants` replaced by ``values``."""
        return self

    def scale_text(self, labels: Mapping[int, str]) -> str:
        """The part of a plan's reason that says which parameters are on which scale.

        ``labels`` names the interval elements by flat index
        (:func:`kohpymc.prior_bounds.interval_labels`); "" when none is rescaled.
        """
        if not self.log_scale.any():
            return ""
        return (
            f"; {int(self.log_scale.sum())} bounded positive parameter(s) on the log scale, "
            "where the posterior is closer to Gaussian"
        )

    def to_value(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``v(w)``, ``dv/dw``, ``d log|dv/dw| / dw`` and ``Σ log|dv/dw|``.

        Elementwise only: the variance-share map (if any) is applied before, by
        :meth:`Reparameterization.logp_dlogp`, which also pulls the gradient back.
        """
        v = np.array(w, dtype=float)
        dv = np.ones_like(v)
        dlogjac = np.zeros_like(v)
        m = self.log_scale
        if not m.any():
            return v, dv, dlogjac, 0.0
        a, b = self.lower[m], self.upper[m]
        if self.walls:
            return self._log_with_walls(w, v, dv, dlogjac, a, b)
        # far out (a planner's probe at ±1.5 sd of a box spanning decades) expit(w) rounds
        # to 0 or 1: x sits on a bound, the Jacobian is 0 and the log density -inf, which
        # the callers handle; numpy's divide/log warnings would only reach the user
        with np.errstate(divide="ignore", invalid="ignore"):
            v[m], g, (s, x, above, below, c, ds) = _log_logit(w[m], a, b)
            dv[m] = g
            dlogjac[m] = (2 * x - a - b) / (above * below) * x * c * ds + c * ds + 1.0 - 2.0 * s
            return v, dv, dlogjac, float(np.sum(np.log(g)))

    def value_and_log_jacobian(self, w: Any, xp: ArrayMath = NUMPY) -> tuple[Any, Any]:
        """``v(w)`` and ``Σ log|dv/dw|`` of the elementwise map, over ``xp``.

        The values of :meth:`to_value` without the derivatives, written for numpy or
        PyTensor (``xp``).  Outside a wall (``walls=True``) the log-Jacobian is ``−inf``
        and the walled elements are evaluated at the walls' midpoint, so that ``v`` and
        a gradient built on it stay finite.

        Examples
        --------
        >>> coords = Coordinates(np.array([True]), np.array([1.0]), np.array([4.0]))
        >>> v, logjac = coords.value_and_log_jacobian(np.array([0.0]))
        >>> bool(np.isclose(v[0], coords.to_value(np.array([0.0]))[0][0]))
        True
        """
        m = self.log_scale
        if not m.any():
            return w, 0.0
        index = np.flatnonzero(m)
        a, b = self.lower[m], self.upper[m]
        w_m = w[index]
        if self.walls:
            x = xp.exp(w_m)
            inside = (x > a) & (x < b)
            w_m = xp.where(inside, w_m, 0.5 * (np.log(a) + np.log(b)))
            v_m, g, _ = _log_walls(w_m, a, b, xp)
            logjac = xp.where(xp.all(inside), xp.sum(xp.log(g)), -np.inf)
        else:
            v_m, g, _ = _log_logit(w_m, a, b, xp)
            logjac = xp.sum(xp.log(g))
        return xp.put(xp.copy(w), index, v_m), logjac

    def _log_with_walls(self, w, v, dv, dlogjac, a, b):
        """``w = ln x``: ``v = ln(x − a) − ln(b − x)``; NaN (zero density) outside."""
        m = self.log_scale
        with np.errstate(all="ignore"):
            v_m, g, (x, above, below) = _log_walls(w[m], a, b)
            inside = (above > 0) & (below > 0)
            v[m] = np.where(inside, v_m, np.nan)
            dv[m] = np.where(inside, g, np.nan)
            dlogjac[m] = np.where(inside, 1.0 - x / above + x / below, np.nan)
            logjac = float(np.sum(np.log(g))) if inside.all() else -np.inf
        return v, dv, dlogjac, logjac

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """``w(v)``, the inverse of the elementwise map and then of the shares."""
        w = np.array(v, dtype=float)
        m = self.log_scale
        if m.any():
            a, b = self.lower[m], self.upper[m]
            x = a + (b - a) * expit(v[m])
            if self.walls:
                w[m] = np.log(x)
            else:
                p = (np.log(x) - np.log(a)) / (np.log(b) - np.log(a))
                p = np.clip(p, 1e-15, 1 - 1e-15)
                w[m] = np.log(p) - np.log1p(-p)
        w = w if self.shares is None else self.shares.inverse(w)
        return w if self.ridge is None else self.ridge.inverse(self, w)


@dataclass(frozen=True)
class VarianceShare:
    r"""Two log standard deviations sampled as log total sd and log ratio.

    When only :math:`\sigma_a^2 + \sigma_b^2` enters the likelihood (measurement noise
    next to an iid discrepancy), the posterior of :math:`(\ln\sigma_a, \ln\sigma_b)`
    is a curved ridge.  In :math:`t = \tfrac12\ln(\sigma_a^2 + \sigma_b^2)`,
    :math:`u = \ln(\sigma_b/\sigma_a)` the data inform ``t`` only and ``u`` follows
    the priors: the ridge is a coordinate axis.  With
    :math:`\ln\sigma_a = t - \tfrac12\,\mathrm{softplus}(2u)` and
    :math:`\ln\sigma_b = \ln\sigma_a + u`, the value-space entry of ``b`` is
    :math:`c\,\ln\sigma_b` (``c = 1`` for a log-transformed sd, ``c = 2`` for a
    log-variance); the map's Jacobian determinant is the constant ``c``.

    Attributes
    ----------
    pairs : tuple of (int, int, float)
        Flat value-space indices of ``ln σ_a`` and of ``b``'s entry, and ``c``.
    names : tuple of (str, str)
        Their parameter names, for the report.
    """

    pairs: tuple[tuple[int, int, float], ...]
    names: tuple[tuple[str, str], ...] = ()

    def forward(self, w: Any, xp: ArrayMath = NUMPY) -> Any:
        """``(t, u)`` entries of ``w`` replaced by ``(ln σ_a, c ln σ_b)`` (over ``xp``)."""
        out = xp.copy(w)
        for i, j, c in self.pairs:
            t, u = w[i], w[j]
            log_a = t - 0.5 * xp.logaddexp(0.0, 2.0 * u)
            out = xp.put(out, i, log_a)
            out = xp.put(out, j, c * (log_a + u))
        return out

    def inverse(self, v: np.ndarray) -> np.ndarray:
        """``(ln σ_a, c ln σ_b)`` entries of ``v`` replaced by ``(t, u)``."""
        out = np.array(v, dtype=float)
        for i, j, c in self.pairs:
            log_b = v[j] / c
            out[i] = 0.5 * np.logaddexp(2.0 * v[i], 2.0 * log_b)
            out[j] = log_b - v[i]
        return out

    def pull_back(self, w: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``w`` from the gradient at :meth:`forward` of ``w``."""
        out = np.array(grad, dtype=float)
        for i, j, c in self.pairs:
            s = expit(2.0 * w[j])
            out[i] = grad[i] + c * grad[j]
            out[j] = -s * grad[i] + c * (1.0 - s) * grad[j]
        return out


@dataclass(frozen=True)
class BoundRidge:
    r"""Other parameters measured from their regression on parameters against a bound.

    A posterior piled against a prior bound ``b`` of ``x`` is sampled in the interval
    transform ``v``, where ``b − x ∝ e^{−v}``: a ridge that is straight in ``x`` (a
    partner ``y`` that compensates ``x`` linearly) bends exponentially in ``v``, and the
    Laplace whitening, fitted at the mode, straightens only its tangent (dielectric M0:
    the log density drops by 214 one Laplace sd along the whitened Φ_B axis, 0.5 for
    a Gaussian).  This map keeps the bounded coordinates ``w_B`` and replaces every other
    coordinate by its deviation from the linear regression on ``x_B`` (in the
    parameters' own units), less its tangent at the mode:
    :math:`w_F = u_F + \beta\,[x_B(u_B) − x_B(\mu_B) − x_B'(\mu_B)(u_B − \mu_B)]`,
    with :math:`\beta = C_{FB} C_{BB}^{-1} / x_B'(\mu_B)` from the Laplace covariance
    ``C`` of ``w``.  The map is the identity to first order at the mode (the whitening
    fitted there stays valid) and unit-triangular (no Jacobian term).

    Attributes
    ----------
    bounded : ndarray of int
        Flat indices ``B`` of the parameters against a bound.
    others : ndarray of int
        Flat indices ``F`` of all other coordinates.
    bounds : (ndarray, ndarray)
        The prior bounds ``a_B``, ``b_B``.
    beta : ndarray
        ``(len(F), len(B))`` regression coefficients.
    centre, slope : ndarray
        ``μ_B``, ``x_B(μ_B)`` and ``x_B'(μ_B)`` are ``centre[0]``, ``centre[1]``, ``slope``.

    Examples
    --------
    >>> coords = Coordinates.identity(2)  # x_0 ~ Uniform(0, 1) in PyMC's logit, y = w_1
    >>> cov = np.array([[1.0, 0.01], [0.01, 0.001]])
    >>> ridge = BoundRidge.fit(coords, np.array([6.0, 0.0]), cov, np.array([0]),
    ...                        (np.array([0.0]), np.array([1.0])))
    >>> u = np.array([3.0, 0.2])
    >>> bool(np.allclose(ridge.inverse(coords, ridge.forward(coords, u)), u))
    True
    """

    bounded: np.ndarray
    others: np.ndarray
    bounds: tuple[np.ndarray, np.ndarray]
    beta: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    centre: tuple[np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0))
    slope: np.ndarray = field(default_factory=lambda: np.zeros(0))

    #: prefix of the kind of a plan whose coordinates carry this map
    prefix: ClassVar[str] = "bound-ridge-"

    def text(self, named: str) -> str:
        """The part of a plan's reason that says what the map does (``named``: ``bounded``)."""
        return (
            f"; {named} against a prior bound: the other coordinates measured from "
            "their regression on it in its own units, which the interval transform bends"
        )

    @classmethod
    def fit(
        cls,
        coords: Coordinates,
        mean: np.ndarray,
        cov: np.ndarray,
        bounded: np.ndarray,
        bounds: tuple[np.ndarray, np.ndarray],
    ) -> BoundRidge:
        """The map for the elements ``bounded`` (prior ``bounds``) from ``w``'s Laplace fit."""
        others = np.setdiff1d(np.arange(mean.size), bounded)
        plain = cls(bounded, others, bounds)
        x, slope = plain.bounded_value(coords, mean)
        cbb = cov[np.ix_(bounded, bounded)]
        beta = cov[np.ix_(others, bounded)] @ np.linalg.inv(cbb) / slope
        return cls(bounded, others, bounds, beta, (mean[bounded].copy(), x), slope)

    def bounded_value(self, coords: Coordinates, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``x_B`` at ``w`` in the parameters' own units, and ``dx_B/dw_B``.

        ``x = a + (b − a)·expit(v)`` after ``coords``' elementwise map (the variance
        shares never touch interval parameters).
        """
        a, b = self.bounds
        v, dv, _, _ = coords.elementwise().to_value(w)
        s = expit(v[self.bounded])
        return self._own_units(v), (b - a) * s * (1.0 - s) * dv[self.bounded]

    def _own_units(self, v: Any, xp: ArrayMath = NUMPY) -> Any:
        """``x_B = a + (b − a)·expit(v_B)`` of a value-space vector ``v``."""
        a, b = self.bounds
        return a + (b - a) * xp.expit(v[self.bounded])

    def _bent(self, x: Any, u: Any) -> Any:
        """``x_B − x_B(μ_B) − x_B'(μ_B)(u_B − μ_B)`` from ``x_B`` at ``u``."""
        mu, x0 = self.centre
        return x - x0 - self.slope * (u[self.bounded] - mu)

    def _bend(self, coords: Coordinates, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The bend (:meth:`_bent`) at ``u`` and its derivative."""
        x, dx = self.bounded_value(coords, u)
        return self._bent(x, u), dx - self.slope

    def forward(self, coords: Coordinates, u: Any, xp: ArrayMath = NUMPY) -> Any:
        """``w`` from the sampling coordinates ``u`` (over ``xp``)."""
        v, _ = coords.elementwise().value_and_log_jacobian(u, xp)
        bend = self._bent(self._own_units(v, xp), u)
        return xp.add(xp.copy(u), self.others, xp.dot(self.beta, bend))

    def inverse(self, coords: Coordinates, w: np.ndarray) -> np.ndarray:
        """``u`` from ``w`` (``u_B = w_B``, so the bend is known from ``w``)."""
        u = np.array(w, dtype=float)
        u[self.others] -= self.beta @ self._bend(coords, w)[0]
        return u

    def pull_back(self, coords: Coordinates, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``u`` from the gradient with respect to ``w``."""
        out = np.array(grad, dtype=float)
        out[self.bounded] += self._bend(coords, u)[1] * (self.beta.T @ grad[self.others])
        return out


def log_coordinates(space: ValueSpace, *, walls: bool = False) -> Coordinates | None:
    """Log-scale coordinates for the positive interval priors of ``space`` (None if none)."""
    kinds = np.array(space.transforms)
    mask = (kinds == "interval") & (space.lower > 0) & np.isfinite(space.upper)
    if not mask.any():
        return None
    return Coordinates(mask, space.lower.copy(), space.upper.copy(), walls)


def _far_from_walls(space: ValueSpace, plan: Reparameterization, n_sd: float = 6.0) -> bool:
    """Whether every wall of the walled log coordinates lies beyond ``n_sd`` posterior sds.

    Judged twice: the Laplace ±``n_sd`` interval of every walled element lies inside its
    bounds, and on each wall the log density, maximised over the other coordinates
    (:func:`_wall_drop`), is at least ``n_sd²/2`` (a Gaussian's drop at ``n_sd`` sds)
    below the mode.  For a Gaussian the two agree; the second catches a tail heavier
    than the Laplace fit.  Two-load beam, noise unknown, M3: the wall E = 300 lies 7.5
    Laplace sds of ln E from the mode but only 8.0 below it in log density, and NUTS
    met it (1 divergence in 4 × 1000 draws, seed 2026; none in four seeds without the
    walls).
    """
    coords = plan.coordinates
    m = coords.log_scale
    sd = np.sqrt(np.einsum("ij,ij->i", plan.chol, plan.chol))[m]
    centre = plan.mean[m]
    lower, upper = np.log(coords.lower[m]), np.log(coords.upper[m])
    if np.any(centre - n_sd * sd <= lower) or np.any(centre + n_sd * sd >= upper):
        return False
    walls = zip(np.flatnonzero(m), lower, upper, strict=True)
    drops = (_wall_drop(space, plan, int(i), w) for i, a, b in walls for w in (a, b))
    return all(drop >= 0.5 * n_sd**2 for drop in drops)


def _wall_drop(space: ValueSpace, plan: Reparameterization, index: int, wall: float) -> float:
    """Log density at the mode minus its maximum over the wall ``u[index] = wall``.

    ``u = μ + L z`` are the plan's unwhitened coordinates (a walled element is an
    interval one, which the shares and the bound ridge leave alone).  The other
    coordinates start from their Laplace conditional mean on the wall and are optimised
    by L-BFGS in units of their Laplace sds; the wall itself is approached to 10⁻⁶ of
    its distance from the mode (its density is zero).
    """
    mean, cov = plan.mean, plan.chol @ plan.chol.T
    unwhitened = replace(plan, chol=np.eye(plan.ndim))
    at = wall + 1e-6 * (mean[index] - wall)
    others = np.arange(plan.ndim) != index
    start = mean[others] + cov[others, index] / cov[index, index] * (at - mean[index])
    scale = np.sqrt(np.diag(cov))[others]

    def objective(y):
        u = np.empty(plan.ndim)
        u[index], u[others] = at, start + scale * y
        logp, grad = unwhitened.logp_dlogp(space, u - mean, safe=True)
        if not np.isfinite(logp) or not np.all(np.isfinite(grad)):
            return np.inf, np.zeros_like(y)
        return -logp, -grad[others] * scale

    y0 = np.zeros(int(others.sum()))
    with np.errstate(all="ignore"):
        best = optimize.minimize(objective, y0, jac=True, method="L-BFGS-B") if y0.size else None
    lowest = objective(y0)[0] if best is None else float(best.fun)
    return float(plan.logp_dlogp(space, np.zeros(plan.ndim), safe=True)[0] + lowest)


@dataclass(frozen=True)
class Mode:
    """The best optimum of the posterior density in value space, with the others found."""

    value: np.ndarray
    logp: float
    optima: list[tuple[float, np.ndarray]] = field(default_factory=list)
    n_starts: int = 0


@dataclass(frozen=True)
class Reparameterization:
    """Whitened sampling coordinates ``z``: ``v = coordinates(μ + L z)``.

    Attributes
    ----------
    kind : str
        ``"none"`` (PyMC's coordinates, started at the mode), ``"affine"`` (whitened
        in PyMC's coordinates), ``"log-affine"`` (positive bounded parameters on the
        log scale, the posterior far inside their bounds, then whitened) or
        ``"log-logit-affine"`` (those parameters as the logit of their position on the
        log scale between the bounds, then whitened) or ``"flat-scale-affine"`` (bounded
        parameters on the scale of their flat prior in a soft box,
        :mod:`kohpymc.flat_scale`); prefixed ``"bound-ridge-"`` with a
        :class:`BoundRidge` and ``"variance-share-"`` with a :class:`VarianceShare`.
    reason : str
        Why this plan, in words (condition number, correlation, or why none).
    value_sd : ndarray or None
        Laplace standard deviations at the mode in PyMC's value space (None without a
        positive-definite Hessian).
    """

    kind: str
    mean: np.ndarray
    chol: np.ndarray
    coordinates: Coordinates
    reason: str
    mode: Mode | None = None
    condition_number: float = float("nan")
    max_correlation: float = float("nan")
    gaussian_score: float = float("nan")
    warnings: tuple[str, ...] = ()
    value_sd: np.ndarray | None = None

    @property
    def ndim(self) -> int:
        """Dimension of the sampling space."""
        return int(self.mean.size)

    def to_value(self, z: np.ndarray) -> np.ndarray:
        """PyMC value-space vector of sampling coordinates ``z``."""
        return self.coordinates.to_value(self._unshared(self.mean + self.chol @ np.asarray(z)))[0]

    def laplace_value_sd(self) -> np.ndarray:
        """Laplace standard deviations at the mode in PyMC's value space.

        The covariance ``L Lᵀ`` of ``w`` carried to ``v`` by the exact Jacobian of the
        map ``w → v`` at ``μ`` (elementwise derivatives after the variance shares).
        """
        inner = np.array([self._pull_back(self.mean, e) for e in np.eye(self.ndim)])
        jac = self.coordinates.to_value(self._unshared(self.mean))[1][:, None] * inner
        factor = jac @ self.chol
        return np.sqrt(np.einsum("ij,ij->i", factor, factor))

    def _unshared(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        """The input of the elementwise map: ``u`` after the bound ridge and the shares."""
        coords = self.coordinates
        w = u if coords.ridge is None else coords.ridge.forward(coords, u, xp)
        return w if coords.shares is None else coords.shares.forward(w, xp)

    def value_from_affine(self, u: Any, xp: ArrayMath = NUMPY) -> tuple[Any, Any]:
        """``v`` and the log-Jacobian of ``u = μ + L z → v`` (constant terms left out).

        Over ``xp``: numpy, or ``kohpymc.native.PYTENSOR`` for a graph.  The bound ridge
        and the variance shares have constant Jacobians, so the log-Jacobian is the
        elementwise map's (:meth:`Coordinates.value_and_log_jacobian`).

        Examples
        --------
        >>> reparam = Reparameterization("none", np.zeros(1), np.eye(1),
        ...                              Coordinates.identity(1), "")
        >>> reparam.value_from_affine(np.array([0.5]))
        (array([0.5]), 0.0)
        """
        return self.coordinates.value_and_log_jacobian(self._unshared(u, xp), xp)

    def _pull_back(self, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``u`` from that with respect to :meth:`_unshared` of ``u``."""
        coords = self.coordinates
        if coords.shares is not None:  # volume-preserving: no log-Jacobian term
            w = u if coords.ridge is None else coords.ridge.forward(coords, u)
            grad = coords.shares.pull_back(w, grad)
        if coords.ridge is not None:  # unit-triangular: no log-Jacobian term
            grad = coords.ridge.pull_back(coords, u, grad)
        return grad

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector."""
        w = self.coordinates.from_value(np.asarray(v, float))
        return np.linalg.solve(self.chol, w - self.mean)

    #: the map ``z -> v`` has a symbolic form over :class:`ArrayMath` (nutpie's native path)
    symbolic: ClassVar[bool] = True

    #: the map follows a curved ridge fitted at a few points (:mod:`kohpymc.bends`): away
    #: from them the curvature in ``z`` is not the mode's, and NUTS takes smaller steps
    #: there (:data:`kohpymc.sampling.CURVED_TARGET_ACCEPT`)
    curved: ClassVar[bool] = False

    def map_constants(self) -> np.ndarray:
        """The map's numbers besides ``μ`` and ``L``, flattened: its coordinates' (if any).

        :mod:`kohpymc.native` passes them to the compiled map as inputs, so that its
        graph, and numba's disk cache of it, does not change with the plan's values.
        """
        return self.coordinates.map_constants()

    def with_map_constants(self, values: Any) -> Reparameterization:
        """The plan with :meth:`map_constants` replaced by ``values`` (e.g. a tensor)."""
        coords = self.coordinates.with_map_constants(values)
        return self if coords is self.coordinates else replace(self, coordinates=coords)

    def logp_dlogp(
        self, space: ValueSpace, z: np.ndarray, *, safe: bool = False
    ) -> tuple[float, np.ndarray]:
        """Log density of ``z`` (exact up to a constant) and its gradient.

        ``safe=True`` returns ``(-inf, nan)`` where the model cannot be evaluated.
        """
        u = self.mean + self.chol @ np.asarray(z, float)
        v, dv, dlogjac, logjac = self.coordinates.to_value(self._unshared(u))
        if not np.isfinite(logjac):  # outside a wall of the log-scale coordinates
            return -np.inf, np.zeros_like(u)
        logp, grad_v = space.logp_dlogp_or_nan(v) if safe else space.logp_dlogp(v)
        return logp + logjac, self.chol.T @ self._pull_back(u, grad_v * dv + dlogjac)

    def to_dict(self) -> dict[str, Any]:
        """Plain description for provenance."""
        return {
            "kind": self.kind,
            "reason": self.reason,
            "log_scale": int(self.coordinates.log_scale.sum()),
            "condition_number": _finite_or_none(self.condition_number),
            "max_abs_correlation": _finite_or_none(self.max_correlation),
            "laplace_gaussian_score": _finite_or_none(self.gaussian_score),
            "mode_log_density": None if self.mode is None else float(self.mode.logp),
            "optimizer_starts": 0 if self.mode is None else int(self.mode.n_starts),
            "warnings": list(self.warnings),
        }


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def prior_scales(space: ValueSpace, seed: int, n: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Per-element location and scale of the prior in value space, from prior draws."""
    import pymc as pm

    model = space.model
    try:
        draws = pm.draw(model.free_RVs, draws=n, random_seed=seed, mode="FAST_COMPILE")
    except NotImplementedError:  # improper priors (pm.Flat) cannot be drawn
        return space.initial.copy(), np.ones(space.ndim)
    if len(model.free_RVs) == 1:
        draws = [draws]
    columns = []
    for rv, values in zip(model.free_RVs, draws, strict=True):
        columns.append(transformed_value(model, rv, values).reshape(n, -1))
    sample = np.concatenate(columns, axis=1)
    q05, q50, q95 = np.nanquantile(sample, [0.05, 0.5, 0.95], axis=0)
    scale = (q95 - q05) / 3.29
    scale = np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
    return q50, scale


def _optimize(space: ValueSpace, start: np.ndarray, center: np.ndarray, scale: np.ndarray):
    """L-BFGS on ``−log p`` in the prior-scaled coordinates ``u = (v − center)/scale``."""

    def objective(u):
        logp, grad = space.logp_dlogp_or_nan(center + scale * u)
        if not np.isfinite(logp) or not np.all(np.isfinite(grad)):
            return np.inf, np.zeros_like(u)
        return -logp, -grad * scale

    u0 = (start - center) / scale
    if not np.isfinite(objective(u0)[0]):
        return None
    with np.errstate(all="ignore"):
        result = optimize.minimize(
            objective,
            u0,
            jac=True,
            method="L-BFGS-B",
            options={"maxiter": 2000, "ftol": 1e-14, "gtol": 1e-9},
        )
    if not np.isfinite(result.fun):
        return None
    return -float(result.fun), center + scale * result.x


def find_mode(
    space: ValueSpace,
    starts: Sequence[np.ndarray] = (),
    *,
    n_design: int = 4,
    max_design: int = 32,
    seed: int = 0,
) -> Mode:
    """Multi-start L-BFGS for the posterior mode in value space.

    The best optimum counts as found when a second start reaches it too (log density
    within :data:`SAME_OPTIMUM` of it).  Until then the Sobol design is doubled, up to
    ``max_design`` starts: a posterior with many local optima — an oscillator's
    frequency, a periodic fit — has a global basin a handful of starts may all miss,
    while on a posterior whose starts agree the first design is all it costs.

    Parameters
    ----------
    space : ValueSpace
    starts : sequence of arrays
        Extra value-space starting points (e.g. a least-squares fit).
    n_design : int
        Number of scrambled-Sobol starts over the central 90 % of the prior (rounded
        up to a power of two; 0 for none).
    max_design : int
        Most Sobol starts when the best optimum is reached by one start only (the design
        is doubled while it is smaller than this; no extra starts with ``n_design=0``).
    seed : int
        Seed of the prior draws and the design.

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu", 0.0, 10.0)
    ...     _ = pm.Normal("y", mu, 1.0, observed=[1.0, 2.0])
    >>> mode = find_mode(value_space(model), seed=1)
    >>> round(float(mode.value[0]), 3)  # (1 + 2) / (2 + 1/100)
    1.493
    """
    center, scale = prior_scales(space, seed)
    candidates = [space.initial, *[np.asarray(s, float) for s in starts]]
    m = int(np.ceil(np.log2(n_design))) if n_design > 0 else -1
    candidates.extend(_design_starts(space.ndim, m, seed, center, scale, first=0))
    optima = _optimize_all(space, candidates, center, scale)
    while m >= 0 and 2**m < max_design and not _confirmed(optima):
        m += 1
        more = _design_starts(space.ndim, m, seed, center, scale, first=2 ** (m - 1))
        candidates.extend(more)
        optima += _optimize_all(space, more, center, scale)
    if not optima:
        raise RuntimeError(
            "the posterior log density is not finite at any starting point "
            f"({len(candidates)} tried): check the priors and the physics model"
        )
    optima.sort(key=lambda item: -item[0])
    best_logp, best = optima[0]
    return Mode(best, best_logp, optima, len(candidates))


#: optima whose log densities differ by less than this count as the same optimum
SAME_OPTIMUM = 1e-3


def _design_starts(ndim: int, m: int, seed: int, center, scale, *, first: int) -> list:
    """Points ``first .. 2**m - 1`` of the scrambled Sobol design over the prior's centre.

    The central 90 % of the prior; a design doubled keeps its first points (the same
    scrambling).
    """
    if m < 0:
        return []
    unit = stats.qmc.Sobol(ndim, scramble=True, seed=seed).random_base2(m)[first:]
    return [center + scale * row for row in stats.norm.ppf(0.05 + 0.9 * unit)]


def _optimize_all(space: ValueSpace, starts: Sequence[np.ndarray], center, scale) -> list:
    found = (_optimize(space, start, center, scale) for start in starts)
    return [f for f in found if f is not None]


def _confirmed(optima: list[tuple[float, np.ndarray]]) -> bool:
    """Whether at least two starts reached the best log density found."""
    if not optima:
        return False
    best = max(logp for logp, _ in optima)
    return sum(best - logp < SAME_OPTIMUM for logp, _ in optima) >= 2


def _hessian(logp_grad, x: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Central-difference Hessian of ``−log p`` from its gradient, symmetrised."""
    hess = np.column_stack([_hessian_column(logp_grad, x, i, steps[i]) for i in range(x.size)])
    return 0.5 * (hess + hess.T)


def _hessian_column(logp_grad, x: np.ndarray, i: int, step: float) -> np.ndarray:
    """Column ``i`` of the Hessian of ``−log p``: central difference of the gradient."""
    e = np.zeros(x.size)
    e[i] = step
    return -(logp_grad(x + e)[1] - logp_grad(x - e)[1]) / (2 * step)


def _local_hessian(logp_grad, x: np.ndarray, tries: int = 4) -> np.ndarray:
    """:func:`_hessian` with each step fitted to the local sd along its axis.

    The first step is :func:`_steps`, which knows only ``|x|``: near ``x = 0`` it is far
    below the posterior sd (the difference is rounding noise), and at ``|x| ≫ sd`` it
    spans many sds.  Each axis is differenced again at 10⁻³ of its conditional sd
    ``1/√H_ii`` until the step lies within 10⁻⁵..10⁻² of it; an axis without positive
    curvature keeps its step.
    """
    columns = []
    for i, step in enumerate(_steps(x)):
        for _ in range(tries):
            column = _hessian_column(logp_grad, x, i, step)
            curvature = column[i]
            if not (np.isfinite(curvature) and curvature > 0):
                break
            sd = 1.0 / np.sqrt(curvature)
            if 1e-5 * sd <= step <= 1e-2 * sd:
                break
            step = 1e-3 * sd
        columns.append(column)
    hess = np.column_stack(columns)
    return 0.5 * (hess + hess.T)


def _laplace(space: ValueSpace, coords: Coordinates, mode_w: np.ndarray):
    """Mode (refined) and Cholesky factor of the Laplace covariance in ``w`` (or None)."""

    def logp_w(w):
        identity = Reparameterization("none", w, np.eye(w.size), coords, "")
        return identity.logp_dlogp(space, np.zeros(w.size), safe=True)

    mode_w = _refine_mode(logp_w, mode_w)
    mode_w = _refine_whitened(logp_w, mode_w)
    mode_w, hess = _newton(logp_w, mode_w)
    chol = _inverse_cholesky(hess)
    if chol is None:  # directions below the differences' resolution: measured again below
        chol = _inverse_cholesky(hess, floor=_PROVISIONAL_FLOOR)
        if chol is None:
            return mode_w, None
        mode_w = _refine_mode(logp_w, mode_w, chol, **_WHITENED_REFINE)
    # second pass: differences along the whitened axes, well scaled whatever the units
    white = Reparameterization("affine", mode_w, chol, coords, "")
    hess_z = _hessian(
        lambda z: white.logp_dlogp(space, z, safe=True),
        np.zeros(mode_w.size),
        np.full(mode_w.size, 1e-3),
    )
    chol_z = _inverse_cholesky(hess_z, resolution=_WHITENED_RESOLUTION)
    if chol_z is None:
        return mode_w, None
    return mode_w, chol @ chol_z


def _newton(logp_w, w: np.ndarray, iterations: int = 6):
    """Newton steps with finite-difference Hessians from ``w``.

    They put the mode within a tiny fraction of a posterior sd, which L-BFGS's stopping
    rule does not do along a narrow ridge.
    """
    logp, grad = logp_w(w)
    hess = _local_hessian(logp_w, w)
    for _ in range(iterations):
        if _inverse_cholesky(hess) is None or not np.all(np.isfinite(grad)):
            break
        step = np.linalg.solve(hess, grad)
        if float(grad @ step) < 1e-10:
            break
        for _ in range(30):
            trial_logp, trial_grad = logp_w(w + step)
            if np.isfinite(trial_logp) and trial_logp >= logp - 1e-9:
                break
            step = step / 2
        else:
            break
        w, logp, grad = w + step, trial_logp, trial_grad
        hess = _local_hessian(logp_w, w)
    return w, hess


def _steps(w: np.ndarray) -> np.ndarray:
    return 1e-5 * np.maximum(np.abs(w), 1e-3)


def _refine_mode(
    logp_w, w0: np.ndarray, chol: np.ndarray | None = None, **options: Any
) -> np.ndarray:
    """Re-optimise the mode in the sampling coordinates (their Jacobian moves it).

    L-BFGS in ``w = w0 + chol u``; ``chol`` defaults to ``diag(max(|w0|, 1))``.
    """

    def objective(w):
        logp, grad = logp_w(w)
        if not np.isfinite(logp):
            return np.inf, np.zeros_like(w)
        return -logp, -grad

    chol = np.diag(np.maximum(np.abs(w0), 1.0)) if chol is None else chol
    with np.errstate(all="ignore"):
        result = optimize.minimize(
            lambda u: (lambda f, g: (f, chol.T @ g))(*objective(w0 + chol @ u)),
            np.zeros_like(w0),
            jac=True,
            method="L-BFGS-B",
            options={"maxiter": 500, **options},
        )
    w = w0 + chol @ result.x
    return w if np.isfinite(result.fun) and result.fun <= objective(w0)[0] else w0


def _refine_whitened(logp_w, w: np.ndarray, rounds: int = 3) -> np.ndarray:
    """:func:`_refine_mode` whitened by the Laplace covariance at ``w``, while it moves.

    Along a narrow ridge (Laplace correlations near 1, condition number 1e7: dielectric
    M3) L-BFGS in per-axis scaling stops several log-density units short of the mode,
    where the Hessian need not be positive definite; whitened, it is well conditioned.
    """
    chol = None
    for _ in range(rounds):
        new_chol = _inverse_cholesky(_local_hessian(logp_w, w))
        chol = chol if new_chol is None else new_chol
        if chol is None:
            return w
        refined = _refine_mode(logp_w, w, chol, **_WHITENED_REFINE)
        if np.all(refined == w):
            return w
        w = refined
    return w


#: along axes already whitened every curvature is ~1; one below this fraction of the largest
#: is flat to the differences' resolution (a + b with flat priors: 1e-9 of the largest, from
#: rounding; the same sum under priors 1e4 wide, a ridge the prior bounds: 0.88)
_WHITENED_RESOLUTION = 1e-6


def _inverse_cholesky(
    hess: np.ndarray, floor: float | None = None, resolution: float = 1e-12
) -> np.ndarray | None:
    """``L`` with ``L Lᵀ = H⁻¹``, or None when ``H`` is not positive definite.

    ``H`` is first scaled to unit diagonal, so parameters whose scales differ by 10¹⁰
    are judged by their correlation, not by their units.  With ``floor``, eigenvalues of
    the scaled ``H`` below ``floor`` times the largest (negative ones included) are
    raised to it: a provisional factor for a Hessian whose weakest directions lie below
    the finite differences' resolution (see :func:`_laplace`).  A scaled eigenvalue at or
    below ``resolution`` times the largest counts as zero (not positive definite).
    """
    if not np.all(np.isfinite(hess)):
        return None
    diag = np.diag(hess)
    if np.any(diag <= 0):
        return None
    d = np.sqrt(diag)
    scaled = hess / np.outer(d, d)
    vals, vecs = np.linalg.eigh(0.5 * (scaled + scaled.T))
    if floor is not None and vals.max() > 0:
        vals = np.maximum(vals, floor * vals.max())
    if vals.min() <= resolution * vals.max():  # scaled eigenvalues: below it counts as flat
        return None
    inverse = (vecs / vals) @ vecs.T
    try:
        return np.linalg.cholesky(0.5 * (inverse + inverse.T)) / d[:, None]
    except np.linalg.LinAlgError:
        return None


def _gaussian_score(space: ValueSpace, reparam: Reparameterization) -> float:
    """Mean |drop of log p at ±1.5 along each axis − 1.125|; 0 for an exact Gaussian."""
    return float(np.mean(_axis_errors(space, reparam)))


def _drop(
    space: ValueSpace, plan: Reparameterization, z: np.ndarray, base: float | None = None
) -> float:
    """``log p(0) − log p(z)`` in ``plan``'s coordinates (inf where ``z`` has no density)."""
    if base is None:
        base, _ = plan.logp_dlogp(space, np.zeros(plan.ndim), safe=True)
    with np.errstate(all="ignore"):
        logp, _ = plan.logp_dlogp(space, z, safe=True)
    return base - logp if np.isfinite(logp) else np.inf


def _axis_drops(space: ValueSpace, plan: Reparameterization, reach: float) -> np.ndarray:
    """:func:`_drop` at ``−reach`` and ``+reach`` along each axis, shape ``(ndim, 2)``."""
    base, _ = plan.logp_dlogp(space, np.zeros(plan.ndim), safe=True)
    drops = np.empty((plan.ndim, 2))
    for i in range(plan.ndim):
        for side, sign in enumerate((-reach, reach)):
            z = np.zeros(plan.ndim)
            z[i] = sign
            drops[i, side] = _drop(space, plan, z, base)
    return drops


def _axis_errors(space: ValueSpace, reparam: Reparameterization) -> np.ndarray:
    """|drop of log p at ±1.5 along each axis − 1.125| (at most 100), per axis and side."""
    drops = _axis_drops(space, reparam, 1.5).ravel()
    return np.minimum(np.abs(drops - _GAUSSIAN_DROP), 100.0)


def _whitened(space: ValueSpace, coords: Coordinates, mode_v: np.ndarray, mode: Mode):
    """The whitened plan in ``coords`` at the mode, or None without a positive Hessian."""
    mode_w, chol = _laplace(space, coords, coords.from_value(mode_v))
    if chol is None:
        return None
    cov = chol @ chol.T
    sd = np.sqrt(np.diag(cov))
    corr = cov / np.outer(sd, sd)
    off = np.abs(corr - np.eye(len(sd)))
    eig = np.linalg.eigvalsh(corr)
    kinds = {
        "value": "affine",
        "log-logit": "log-logit-affine",
        "log": "log-affine",
        "soft-flat-scale": "flat-scale-affine",
    }
    kind = kinds[coords.name.removeprefix("bound-ridge-")]
    kind = kind if coords.ridge is None else f"{coords.ridge.prefix}{kind}"
    kind = kind if coords.shares is None else f"variance-share-{kind}"
    kind = getattr(coords, "kind_prefix", "") + kind
    plan = Reparameterization(
        kind,
        mode_w,
        chol,
        coords,
        "",
        mode,
        condition_number=float(eig.max() / eig.min()),
        max_correlation=float(off.max()) if off.size else 0.0,
    )
    score = _gaussian_score(space, plan)
    return Reparameterization(
        **{**plan.__dict__, "gaussian_score": score, "value_sd": plan.laplace_value_sd()}
    )


def plan(
    space: ValueSpace,
    starts: Sequence[Mapping[str, Any] | np.ndarray] = (),
    *,
    seed: int = 0,
    n_design: int = 4,
    shares: VarianceShare | None = None,
) -> Reparameterization:
    """Find the mode and choose the sampling coordinates (see the module docstring).

    Parameters
    ----------
    space : ValueSpace
    starts : sequence
        Extra starting points, as value-space vectors or as ``{value-variable name:
        value}`` points.
    seed : int
        Seed of the prior draws and the start design.
    n_design : int
        Number of space-filling starts from the prior.
    shares : VarianceShare, optional
        Pairs of standard deviations of which only the sum of squares is identified;
        they are sampled as total sd and log ratio in every coordinate system.

    Returns
    -------
    Reparameterization

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     a = pm.Normal("a", 0.0, 1e5)
    ...     b = pm.Normal("b", 0.0, 1e-5)
    ...     _ = pm.Normal("y", 1e-5 * a + 1e5 * b, 0.01, observed=[1.0])
    >>> reparam = plan(value_space(model), seed=1)
    >>> reparam.kind, reparam.max_correlation > 0.99
    ('affine', True)
    """
    vectors = [s if isinstance(s, np.ndarray) else space.join(dict(s)) for s in starts]
    mode = find_mode(space, vectors, seed=seed, n_design=n_design)
    pymc_coords, candidates = _candidate_coordinates(space, shares)
    plans = [p for p in (_whitened(space, c, mode.value, mode) for c in candidates) if p]
    plans = [p for p in plans if not p.coordinates.walls or _far_from_walls(space, p)]
    plans += _near_bound_plans(space, plans, mode)
    plans += _bound_ridge_plans(space, plans, mode)
    shared = _shares_text(shares)
    if not plans:
        return _flat_plan(space, pymc_coords, mode, shared)
    best = min(plans, key=lambda p: p.gaussian_score)
    box = box_ridge_plan(space, mode, shares=shares)
    # a flat ridge ending on the box goes along its segment whenever that fits: even from
    # corner to corner, where a Laplace map fits near the mode (k·c = 100, k and c
    # log-uniform over 1e-8..1e-6 and 1e8..1e10: score 0.19 against the segment's 0.27),
    # NUTS diverges at the ridge's ends (3 seeds, 4 × 1000: 11-18 divergences, ESS 95-264;
    # along the segment 0 and 4186-4346)
    along: list[Reparameterization] = []
    if box is not None and box.gaussian_score < max(best.gaussian_score, _BOX_RIDGE_SCORE):
        along.append(_box_ridge_reason(space, box, best))
    one_sided = box is None or box.gaussian_score > _BOX_RIDGE_SCORE
    curve = (
        _ridge_curve(space, plans, mode, one_sided=one_sided)
        if best.gaussian_score > _BOX_RIDGE_SCORE
        else None
    )
    if curve is not None and curve.gaussian_score < best.gaussian_score:
        along.append(_ridge_curve_reason(space, curve, best))
    segment = _ridge_segment(space, mode, seed, shares, best)
    if segment is not None:
        along.append(segment)
    if not along:
        best = _flat_scale_or(space, plans, mode, seed, shares, best)
        bent = _bent(space, best)
        # no map along a ridge to compete with: a ridge that bends too fast for a parabola
        # is followed along its conditional modes (dielectric M3: score 22.5 -> 0.26)
        if bent is None or bent.gaussian_score > _FOLLOW_SCORE:
            followed = _followed(space, best)
            if followed is not None and (
                bent is None or followed.gaussian_score < bent.gaussian_score
            ):
                bent = followed
        if bent is None and not _needs_whitening(best):
            return _unwhitened_plan(space, pymc_coords, mode, best, shares, shared, seed)
        white = _whitened_plan(space, mode, best, shared, seed)
        return white if bent is None else bent.explained(white)
    # the maps along a ridge compete with the bent Laplace map on the same score; a plan
    # with zero-density holes where the sampler goes (a straight segment that misses the box
    # when a parameter near its own bound crosses its wall: dielectric M2, 129 divergences in
    # 2 × 300 draws) ranks after every plan without
    choices = list(along)
    bent = _bent(space, best)
    if bent is not None:
        choices.append(bent.explained(_whitened_plan(space, mode, best, shared, seed)))
    holes = len(choices) > 1
    return min(choices, key=lambda p: (holes and _has_holes(space, p, seed), p.gaussian_score))


def _near_bound_plans(
    space: ValueSpace, plans: list[Reparameterization], mode: Mode
) -> list[Reparameterization]:
    """Candidates sampling near-bound parameters by their distance to the bound."""
    from kohpymc.bound_distance import bound_distance_plans

    return bound_distance_plans(space, plans, mode)


def _flat_scale_or(
    space: ValueSpace,
    plans: list[Reparameterization],
    mode: Mode,
    seed: int,
    shares: VarianceShare | None,
    best: Reparameterization,
) -> Reparameterization:
    """``best``, or the Laplace map with bounded parameters on their prior's flat scale.

    That map (:mod:`kohpymc.flat_scale`) replaces ``best`` when it fits at least as well
    at ±1.5 sds and its axes' mean error at ±3 sds (:func:`_far_error`) is below
    ``_FLAT_GAIN`` of ``best``'s: the two agree near the mode, and the flat scale keeps a
    ridge straight further out (creep M0: 1.50 → 0.35; 16–23 divergences → 0).  Where they
    fit alike, ``best`` stays (its map is the one nutpie's native path runs without
    compiling).
    """
    from kohpymc.flat_scale import flat_scale_plans

    found = flat_scale_plans(space, plans, mode, seed, shares)
    if not found or found[0].gaussian_score > best.gaussian_score:
        return best
    if _far_error(space, found[0]) < _FLAT_GAIN * _far_error(space, best):
        return found[0]
    return best


#: share of the best map's error at ±3 sds below which the flat-scale map replaces it
_FLAT_GAIN = 0.5


def _far_error(space: ValueSpace, plan: Reparameterization, reach: float = 3.0) -> float:
    """Mean |drop of log p at ±``reach`` along each axis − ``reach²/2``| (each at most 100)."""
    drops = _axis_drops(space, plan, reach).ravel()
    return float(np.mean(np.minimum(np.abs(drops - 0.5 * reach**2), 100.0)))


def _bent(space: ValueSpace, best: Reparameterization) -> Any:
    """``best`` bent along a parabolic ridge (:mod:`kohpymc.bends`), or None."""
    if not best.gaussian_score > _BEND_SCORE:
        return None
    from kohpymc.bends import bend_plan

    return bend_plan(space, best)


def _followed(space: ValueSpace, best: Reparameterization) -> Any:
    """``best`` with its worst axes followed along the ridge (:func:`kohpymc.bends.follow_plan`).

    Tried when no parabola helped and ``best`` fits badly on average (score above
    ``_FOLLOW_SCORE``); None otherwise.
    """
    if type(best) is not Reparameterization or not best.gaussian_score > _FOLLOW_SCORE:
        return None
    from kohpymc.bends import follow_plan

    return follow_plan(space, best)


def _bound_ridge_plans(
    space: ValueSpace, plans: list[Reparameterization], mode: Mode
) -> list[Reparameterization]:
    """Each of ``plans`` with a :class:`BoundRidge` where a bound is near (see below).

    Near means within ``MODE_SDS`` Laplace sds of the mode; when no parameter is that near
    and every plan fits badly (score above ``_FOLLOW_SCORE``), within ``_FAR_BOUND_SDS``:
    a Laplace map that fits badly understates how far its ridge runs, and a bound further
    out can still end it (Steinhart-Hart with a constant bias: C's upper bound 3.1 Laplace
    sds from the mode; the ridge, followed in interval coordinates, ends on a wall there,
    log density −77 at 3 sds; measured from C in its own units it runs on smoothly).
    """
    ridged = [p for p in (_bound_ridge_plan(space, p, mode) for p in plans) if p]
    if ridged or not plans or min(p.gaussian_score for p in plans) <= _FOLLOW_SCORE:
        return ridged
    far = (_bound_ridge_plan(space, p, mode, sds=_FAR_BOUND_SDS) for p in plans)
    return [p for p in far if p]


def _bound_ridge_plan(
    space: ValueSpace, laplace: Reparameterization, mode: Mode, *, sds: float = MODE_SDS
) -> Reparameterization | None:
    """``laplace``'s coordinates with a :class:`BoundRidge`, or None.

    For the parameters whose mode lies within ``sds`` Laplace sds of a prior bound
    (:func:`kohpymc.prior_bounds.hits_at_mode`); None when there are none.
    """
    if laplace.coordinates.walls or laplace.value_sd is None:
        return None
    hits = hits_at_mode(space, mode.value, laplace.value_sd, sds=sds)
    bounded = np.unique(np.array([hit.index for hit in hits], dtype=int))
    if bounded.size == 0 or bounded.size == laplace.ndim:
        return None
    cov = laplace.chol @ laplace.chol.T
    bounds = (space.lower[bounded], space.upper[bounded])
    ridge = BoundRidge.fit(laplace.coordinates, laplace.mean, cov, bounded, bounds)
    return _whitened(space, laplace.coordinates.with_ridge(ridge), mode.value, mode)


def _candidate_coordinates(
    space: ValueSpace, shares: VarianceShare | None
) -> tuple[Coordinates, list[Coordinates]]:
    """PyMC's coordinates, and every coordinate system to try (PyMC's, then the logs)."""
    pymc_coords = Coordinates.identity(space.ndim).with_shares(shares)
    candidates = [pymc_coords]
    for walls in (False, True):
        log_coords = log_coordinates(space, walls=walls)
        if log_coords is not None:
            candidates.append(log_coords.with_shares(shares))
    return pymc_coords, candidates


def _flat_plan(
    space: ValueSpace, pymc_coords: Coordinates, mode: Mode, shared: str
) -> Reparameterization:
    """No plan has a positive Hessian: PyMC's coordinates from the mode, with a warning.

    The warning names the cause: a flat direction, or, when the Hessian changes with the
    finite-difference step (:func:`_hessian_noise`), a gradient too noisy to difference.
    """
    start = pymc_coords.from_value(mode.value)
    noise = _hessian_noise(space, pymc_coords, start)
    if noise > _NOISY_HESSIAN:
        warning = (
            f"the gradient of the log density is noisy at the mode: its finite-difference "
            f"Hessian changes by {noise:.0%} when the step grows tenfold (a solver tolerance, "
            "or finite differences of a simulator whose output jitters with the "
            "parameters), so no Laplace map was computed; give the physics an exact "
            "Jacobian, or if the sampler reports trouble use sampler='smc'"
        )
    else:
        warning = (
            "the posterior is flat in some direction at its mode: a combination of "
            "parameters the data and priors do not inform (see the identifiability "
            "report); NUTS may need very long trajectories there"
        )
    return Reparameterization(
        "none",
        start,
        np.eye(space.ndim),
        pymc_coords,
        shared + "the Hessian of the log density is not positive definite at the mode "
        "(a flat direction, a saddle or a noisy gradient): sampling in PyMC's coordinates "
        "from the mode",
        mode,
        warnings=(warning,),
    )


#: relative change of the finite-difference Hessian, step ×10, that marks a noisy gradient
#: (a simulator whose output jitters by 1e-5 relative, under a finite-difference Jacobian:
#: 0.9; a smooth log density: truncation error only)
_NOISY_HESSIAN = 0.5


def _hessian_noise(space: ValueSpace, coords: Coordinates, w: np.ndarray) -> float:
    """‖H(10h) − H(h)‖ / max ‖H‖ of the central-difference Hessians at ``w`` (Frobenius)."""
    identity = Reparameterization("none", w, np.eye(w.size), coords, "")

    def logp_w(x):
        return identity.logp_dlogp(space, x - w, safe=True)

    first, second = (_hessian(logp_w, w, k * _steps(w)) for k in (1.0, 10.0))
    if not (np.all(np.isfinite(first)) and np.all(np.isfinite(second))):
        return float("inf")
    scale = max(np.linalg.norm(first), np.linalg.norm(second), np.finfo(float).tiny)
    return float(np.linalg.norm(first - second) / scale)


def _unwhitened_plan(
    space: ValueSpace,
    pymc_coords: Coordinates,
    mode: Mode,
    best: Reparameterization,
    shares: VarianceShare | None,
    shared: str,
    seed: int,
) -> Reparameterization:
    """Well conditioned at the mode: PyMC's coordinates, with the best plan's diagnostics."""
    return Reparameterization(
        "none" if shares is None else "variance-share",
        pymc_coords.from_value(mode.value),
        np.eye(space.ndim),
        pymc_coords,
        shared + f"well conditioned at the mode (condition number {best.condition_number:.3g}, "
        f"max |correlation| {best.max_correlation:.3f}, sd ratio "
        f"{_sd_ratio(best):.3g}): PyMC's coordinates, chains started around the mode",
        mode,
        condition_number=best.condition_number,
        max_correlation=best.max_correlation,
        gaussian_score=best.gaussian_score,
        warnings=_separated_modes(space, best, mode) + _gradient_mismatch(space, best, seed),
        value_sd=best.value_sd,
    )


def _whitened_plan(
    space: ValueSpace, mode: Mode, best: Reparameterization, shared: str, seed: int
) -> Reparameterization:
    """The best whitened plan, with its reason and warnings."""
    reason = shared + (
        f"whitened by the Laplace covariance at the mode (condition number "
        f"{best.condition_number:.3g}, max |correlation| {best.max_correlation:.4f}"
        + best.coordinates.scale_text(interval_labels(space))
        + _ridge_text(space, best)
        + ")"
    )
    return Reparameterization(
        **{
            **best.__dict__,
            "reason": reason,
            "warnings": _separated_modes(space, best, mode) + _gradient_mismatch(space, best, seed),
        }
    )


def _ridge_text(space: ValueSpace, plan: Reparameterization) -> str:
    """The bound-ridge part of a plan's reason ("" without a ridge map)."""
    ridge = plan.coordinates.ridge
    if ridge is None:
        return ""
    by_index = interval_labels(space)
    return ridge.text(", ".join(by_index[int(i)] for i in ridge.bounded))


def _shares_text(shares: VarianceShare | None) -> str:
    """The variance-share part of a plan's reason ("" without shares)."""
    if shares is None or not shares.pairs:
        return ""
    named = ", ".join(f"{a} and {b}" for a, b in shares.names) or "a pair of sds"
    return (
        f"{named} sampled as log of sqrt(sum of squares) and log of their ratio (only the "
        "sum of squares is identified); "
    )


def _sd_ratio(plan: Reparameterization) -> float:
    """Largest over smallest Laplace sd of the sampling coordinates."""
    sd = np.sqrt(np.einsum("ij,ij->i", plan.chol, plan.chol))
    return float(sd.max() / sd.min())


def _needs_whitening(plan: Reparameterization) -> bool:
    """Whether the posterior is strongly correlated or badly scaled at the mode.

    |ρ| > 0.95, condition number > 100 or sd ratio > 100; or, where the Laplace map fits
    well (Gaussian score < 0.1), condition number or sd ratio > 10.  Otherwise nutpie's own
    mass-matrix adaptation copes, and the Laplace map of a posterior that is far from
    Gaussian (e.g. GP hyper-parameters: 2 divergences on a time series under M5, 0
    without the map) can only hurt.
    """
    ratio = _sd_ratio(plan)
    strongly = plan.max_correlation > 0.95 or plan.condition_number > 100 or ratio > 100
    # a Laplace map that fits well (log-density drops within 0.1 of a Gaussian's) also pays
    # on milder anisotropy: a decay model's V0/tau/offset (condition number 16, score 0.05)
    # reached bulk ESS 302 of 1000 draws without it
    accurate = plan.gaussian_score < 0.1 and (plan.condition_number > 10 or ratio > 10)
    return strongly or accurate


def _gradient_mismatch(
    space: ValueSpace, white: Reparameterization, seed: int, tol: float = 1e-3, step: float = 1e-2
) -> tuple[str, ...]:
    """A warning when the gradient disagrees with finite differences of the log density.

    Checked in whitened coordinates (posterior sd 1 on every axis, whatever the units)
    at three points about one sd from the mode, along random directions: a wrong
    physics Jacobian, or a simulator whose output is noisy at the scale of the posterior,
    shows up as a directional derivative that central differences (step ``step`` sd) do not
    reproduce to a relative ``tol``.  The step is a hundredth of a posterior sd, near the
    scale of a leapfrog step's variation, so round-off far below it (an emulator's
    predictive covariance is noisy at ~1e-7 in the log density, which a 1e-4 sd step
    turned into a relative error of 4e-3) is not reported, while the truncation error of
    a near-Gaussian density stays ~1e-5.
    """
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(3):
        z = rng.normal(size=white.ndim)
        e = rng.normal(size=white.ndim)
        e /= np.linalg.norm(e)
        logp, grad = white.logp_dlogp(space, z, safe=True)
        up, _ = white.logp_dlogp(space, z + step * e, safe=True)
        down, _ = white.logp_dlogp(space, z - step * e, safe=True)
        if not np.isfinite([logp, up, down]).all() or not np.all(np.isfinite(grad)):
            continue
        analytic, numeric = float(grad @ e), (up - down) / (2.0 * step)
        worst = max(worst, abs(analytic - numeric) / (abs(analytic) + abs(numeric) + 1e-3))
    if worst <= tol:
        return ()
    return (
        f"the gradient of the log density disagrees with finite differences of it (relative "
        f"error {worst:.2g} about one posterior sd from the mode): a wrong physics Jacobian "
        "or a simulator too noisy for gradients; check the Jacobian, or use sampler='smc'",
    )


#: optima this many Laplace sds (of the best mode) from the best, and from each other, are
#: separate modes; closer ones are the same optimum found from several starts
MODE_SEPARATION = 6.0


def _separated_modes(space: ValueSpace, best: Reparameterization, mode: Mode) -> tuple[str, ...]:
    """A warning naming the other optima nearly as high, many Laplace sds from the best.

    Optima found from several starts near one another count once, and the warning gives
    the parameter values at the best mode and at the others (the user's units), so a
    symmetry of the model (two rate constants that can swap) shows in the numbers.
    """
    kept: list[tuple[float, np.ndarray, np.ndarray]] = []  # (logp, z, value) per mode
    for logp, value in mode.optima[1:]:
        if logp < mode.logp - 10.0:
            continue
        z = best.from_value(value)
        if not np.isfinite(np.linalg.norm(z)) or np.linalg.norm(z) <= MODE_SEPARATION:
            continue
        if all(np.linalg.norm(z - other) > MODE_SEPARATION for _, other, _ in kept):
            kept.append((logp, z, value))
    if not kept:
        return ()
    nearest = min(float(np.linalg.norm(z)) for _, z, _ in kept)
    others = ", ".join(
        f"another at {_named_point(space, value)} (log density {mode.logp - logp:.2g} lower)"
        for logp, _, value in kept[:3]
    )
    more = "" if len(kept) <= 3 else f" and {len(kept) - 3} more"
    return (
        f"the posterior has {len(kept) + 1} separated modes (log density within 10 of the "
        f"best, {nearest:.0f}+ Laplace sds apart): the best at "
        f"{_named_point(space, mode.value)}, {others}{more}; NUTS chains may each stay in "
        "one mode, so the posterior may describe only one: narrow the priors to one mode if "
        "the physics allows it (an order between two rates), or try sampler='smc' and "
        "check that its chains agree",
    )


def _named_point(space: ValueSpace, value: np.ndarray, most: int = 6) -> str:
    """``{a=1.17, b=0.122}``: the scalar parameters at a value-space point (at most ``most``)."""
    try:
        expanded = space.expand(value)
    except Exception:  # noqa: BLE001 - only words for a warning
        return "(values not available)"
    scalars = [  # "<name>_white": a formulation's non-centred auxiliary, not a parameter
        (k, float(np.ravel(v)[0]))
        for k, v in expanded.items()
        if np.size(v) == 1 and not k.endswith("_white")
    ]
    text = ", ".join(f"{k}={v:.3g}" for k, v in scalars[:most])
    return "{" + text + (", ..." if len(scalars) > most else "") + "}"


@dataclass(frozen=True)
class BoxRidgePlan(Reparameterization):
    r"""Sampling along a flat ridge that ends on the prior box: ``z = (y, t)``.

    When the data inform only a combination of bounded positive parameters (``y = k c x``
    with ``k`` and ``c`` in prior boxes), the posterior in ``ℓ = ln θ`` is a thin straight
    ridge along a direction ``d``, flat (log-uniform priors) or nearly so, cut off where
    it leaves the box; no Gaussian fits it, and in PyMC's (logit) coordinates it bends
    into an L whose arms run off to infinity (r̂ 1.1–1.6, 100–200 divergences).  Here
    ``ℓ = ℓ₀ + B y + s d``: ``B`` whitens the informed directions (Laplace in ``ℓ``) and
    the position along the ridge ``s = s_lo(y) + (s_hi(y) − s_lo(y))·expit(t)`` is
    squeezed between the box faces the line through ``ℓ₀ + B y`` meets, so every ``t`` is
    inside the box and a flat ridge is a logistic density in ``t``.  The Jacobian is
    ``(s_hi − s_lo)·expit'(t)`` times a constant; the elementwise map ``ℓ → v`` is the
    log scale with walls (:class:`Coordinates`), preceded by the variance shares (if any)
    on the other coordinates of ``ℓ``.

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> from kohpymc.priors import LogUniform
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     k = LogUniform(1e-8, 1e-6).create("k")
    ...     c = LogUniform(1e8, 1e10).create("c")
    ...     _ = pm.Normal("y", k * c * np.linspace(0, 1, 20), 0.5,
    ...                   observed=30 * np.linspace(0, 1, 20))
    >>> space = value_space(model)
    >>> box = box_ridge_plan(space, find_mode(space, seed=1))
    >>> box.kind, box.ndim
    ('box-ridge-log', 2)
    >>> v = box.to_value(np.array([0.3, -1.2]))
    >>> bool(np.allclose(box.to_value(box.from_value(v)), v))
    True
    """

    symbolic: ClassVar[bool] = False  # its own map, in numpy only

    origin: np.ndarray = field(default_factory=lambda: np.zeros(0))
    basis: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    precision_sqrt: np.ndarray = field(default_factory=lambda: np.zeros(0))
    direction: np.ndarray = field(default_factory=lambda: np.zeros(0))
    box: tuple[np.ndarray, np.ndarray, np.ndarray] = (np.zeros(0), np.zeros(0), np.zeros(0))

    def _segment(self, y: np.ndarray):
        """``ℓ₀ + B y``, ``s_lo``, ``s_hi`` and their gradients in ``y``."""
        index, lo, hi = self.box
        centre = self.origin + self.basis @ y
        d = self.direction[index]
        enter = np.where(d > 0, lo - centre[index], hi - centre[index]) / d
        leave = np.where(d > 0, hi - centre[index], lo - centre[index]) / d
        i_lo, i_hi = int(np.argmax(enter)), int(np.argmin(leave))
        rows = self.basis[index]
        return (
            centre,
            float(enter[i_lo]),
            -rows[i_lo] / d[i_lo],
            float(leave[i_hi]),
            -rows[i_hi] / d[i_hi],
        )

    def _position(self, z: np.ndarray):
        z = np.asarray(z, float)
        y, t = z[:-1], float(z[-1])
        centre, s_lo, d_lo, s_hi, d_hi = self._segment(y)
        sig = float(expit(t))
        width = s_hi - s_lo
        return y, t, sig, centre + (s_lo + width * sig) * self.direction, width, d_lo, d_hi

    def to_value(self, z: np.ndarray) -> np.ndarray:
        """PyMC value-space vector of sampling coordinates ``z``."""
        return self.coordinates.to_value(self._unshared(self._position(z)[3]))[0]

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector (ends of the ridge clipped)."""
        ell = self.coordinates.from_value(np.asarray(v, float))
        r = ell - self.origin
        y = (self.basis.T @ r) * self.precision_sqrt**2
        _, s_lo, _, s_hi, _ = self._segment(y)
        frac = np.clip((self.direction @ r - s_lo) / (s_hi - s_lo), 1e-9, 1 - 1e-9)
        return np.append(y, np.log(frac) - np.log1p(-frac))

    def laplace_value_sd(self) -> np.ndarray:  # pragma: no cover - not a Laplace map
        return np.full(self.ndim, np.nan)

    def logp_dlogp(
        self, space: ValueSpace, z: np.ndarray, *, safe: bool = False
    ) -> tuple[float, np.ndarray]:
        """Log density of ``z`` (exact up to a constant) and its gradient."""
        y, t, sig, ell, width, d_lo, d_hi = self._position(z)
        if not width > 0:
            return -np.inf, np.zeros(self.ndim)
        v, dv, dlogjac, logjac = self.coordinates.to_value(self._unshared(ell))
        if not np.isfinite(logjac):
            return -np.inf, np.zeros(self.ndim)
        logp, grad_v = space.logp_dlogp_or_nan(v) if safe else space.logp_dlogp(v)
        g = self._pull_back(ell, grad_v * dv + dlogjac)
        along = float(self.direction @ g)
        grad_y = self.basis.T @ g + along * ((1 - sig) * d_lo + sig * d_hi) + (d_hi - d_lo) / width
        grad_t = along * width * sig * (1 - sig) + 1.0 - 2.0 * sig
        log_sig = -np.logaddexp(0.0, -t) - np.logaddexp(0.0, t)
        return logp + logjac + np.log(width) + log_sig, np.append(grad_y, grad_t)


def box_ridge_plan(
    space: ValueSpace, mode: Mode, flat: float = 1e-6, shares: VarianceShare | None = None
) -> BoxRidgePlan | None:
    """A :class:`BoxRidgePlan` for a flat direction in the log of bounded parameters.

    None unless the posterior at ``mode`` has one.  Flat: the smallest eigenvalue of the
    Hessian of ``−log p`` in ``ℓ`` is below ``flat`` times the largest; the direction
    lies (99 % of its weight) in bounded positive parameters; every other eigenvalue is
    positive.  ``shares`` (variance shares, :class:`VarianceShare`) act on the other
    coordinates of ``ℓ`` as in every other plan.
    """
    coords = log_coordinates(space, walls=True)
    if coords is None or coords.log_scale.sum() < 2:
        return None
    coords = coords.with_shares(shares)
    ell0 = coords.from_value(mode.value)
    identity = Reparameterization("none", ell0, np.eye(ell0.size), coords, "")
    with np.errstate(all="ignore"):
        hess = _local_hessian(lambda w: identity.logp_dlogp(space, w - ell0, safe=True), ell0)
    if not np.all(np.isfinite(hess)):
        return None
    lam, vec = np.linalg.eigh(hess)
    if lam[-1] <= 0 or abs(lam[0]) > flat * lam[-1] or np.any(lam[1:] <= 0):
        return None
    d = vec[:, 0].copy()
    mask = coords.log_scale
    if float(d[mask] @ d[mask]) < 0.99:
        return None
    d[~mask] = 0.0
    d /= np.linalg.norm(d)
    index = np.flatnonzero(mask & (np.abs(d) > 1e-9))
    box = (index, np.log(coords.lower[index]), np.log(coords.upper[index]))
    root = np.sqrt(lam[1:])
    plan = BoxRidgePlan(
        "box-ridge-log",
        np.zeros(ell0.size),
        np.eye(ell0.size),
        coords,
        "",
        mode,
        origin=ell0 - (d @ ell0) * d,
        basis=vec[:, 1:] / root,
        precision_sqrt=root,
        direction=d,
        box=box,
    )
    if not np.isfinite(plan.logp_dlogp(space, plan.from_value(mode.value), safe=True)[0]):
        return None
    return replace(plan, gaussian_score=_gaussian_score(space, plan))


def _ridge_curve(
    space: ValueSpace, plans: Sequence[Reparameterization], mode: Mode, *, one_sided: bool = False
) -> Reparameterization | None:
    """The ridge-curve plan from the log-logit Laplace plan (None without a long ridge).

    With ``one_sided`` (no flat ridge along a segment of the box fits), a shorter
    ridge is followed too (a pivot whose marginal sd exceeds its conditional sd
    ``_ONE_SIDED_RATIO`` times).
    """
    from kohpymc.ridge_curve import ridge_curve_plan

    log_logit = [p for p in plans if p.coordinates.name == "log-logit"]
    value = [p for p in plans if p.coordinates.name == "value"]
    curve = None
    if log_logit:
        curve = ridge_curve_plan(space, log_logit[0], mode)
        if curve is None and one_sided:
            # a ridge the data bound on one side only: short at the mode, where the Laplace
            # map fits, then flat out to a face of the box (substrate inhibition's K_i:
            # marginal over conditional sd 5 at the mode, best Laplace map 3.3, bent 0.35
            # with 42 divergences; followed, its pivot warped to normal quantiles, 0.04)
            curve = ridge_curve_plan(space, log_logit[0], mode, min_ratio=_ONE_SIDED_RATIO)
    elif value:
        # no log scale (no interval prior on the positive axis): the ridge is led by a
        # parameter in its own units (Steinhart–Hart's C, whose box spans zero)
        curve = ridge_curve_plan(space, value[0], mode, own=True)
    if curve is None or not curve.gaussian_score > _BEND_SCORE:
        return curve
    from kohpymc.bends import bend_coordinates

    # across the ridge two parameters may still trade off nonlinearly (dielectric M2: the
    # ε_∞–E_A parabola, drop 44 at ±2 sd along ε_∞'s axis, 2.0 for a Gaussian)
    return bend_coordinates(space, curve) or curve


def _ridge_segment(
    space: ValueSpace,
    mode: Mode,
    seed: int,
    shares: VarianceShare | None,
    best: Reparameterization,
) -> Reparameterization | None:
    """The ridge-segment plan when the best Laplace map fits badly and it fits better.

    Badly: on average (score above ``_BOX_RIDGE_SCORE``) or along one axis (M3 on an
    Arrhenius ridge cut by a face: drops of 5.3 and 10.9 at ±1.5 sd where a Gaussian
    drops 1.125, hidden in a mean of 0.68 over eleven axes; 48 divergences).
    """
    if best.gaussian_score <= _BOX_RIDGE_SCORE and (
        _axis_errors(space, best).max() <= _BOX_RIDGE_SCORE
    ):
        return None
    from kohpymc.ridge_segment import segment_plan, segment_reason

    segment = segment_plan(space, mode, seed, shares)
    if segment is None or not segment.gaussian_score < best.gaussian_score:
        return None
    if _has_flat_axis(space, segment):
        return None
    # a walled element with a tiny component along the ridge empties the segment wherever
    # the whitened centre lies beyond its wall (box-ridge-log on dielectric M2): never used
    return None if _has_holes(space, segment, seed) else segment_reason(space, segment, best)


def _has_flat_axis(space: ValueSpace, plan: Reparameterization, reach: float = 3.0) -> bool:
    """Whether some axis of ``plan`` has lost its scale.

    Its log density changes by less than 0.01 at ±``reach`` (a Gaussian's drops 4.5 at
    ±3), so NUTS would wander along it (Steinhart–Hart with a constant bias: the ridge
    segment's position axis dropped 0.0 at ±3; 201 divergences in 2 × 1000 draws).
    """
    return bool(np.any(np.abs(_axis_drops(space, plan, reach)).max(axis=1) < 0.01))


def _ridge_curve_reason(space: ValueSpace, curve: Any, best: Reparameterization):
    """``curve`` with its reason: which parameters lead the ridge, and the scores."""
    by_index = interval_labels(space)
    ridge = getattr(curve, "inner", curve)  # the curve itself, or the one bent
    coords = ridge.coordinates
    soft = ", ".join(by_index[int(i)] for i in np.flatnonzero(coords.soft))
    near = "" if coords.ridge is None else ", ".join(by_index[int(i)] for i in coords.ridge.bounded)
    bend = getattr(curve, "bend", None)
    return replace(
        curve,
        reason=(
            f"the posterior is a curved ridge led by {by_index[int(ridge.pivot)]} from one "
            f"face of its prior box to the other (Gaussian score of the best Laplace map "
            f"{best.gaussian_score:.3g}, of this map {curve.gaussian_score:.3g}): sampled "
            f"along it by the logit of {by_index[int(ridge.pivot)]}'s position in its box "
            f"and across it whitened around the conditional modes at {ridge.nodes.size} "
            "nodes"
            + (f"; {soft} in their own units in a soft box" if soft else "")
            + (
                f"; {near} near a bound, the others following what the box leaves of it"
                if near
                else ""
            )
            + (f"; {len(bend.axes)} axis/axes bent along the conditional modes" if bend else "")
            + (
                f", {len(bend.surfaces)} pair(s) of axes jointly"
                if bend is not None and bend.surfaces
                else ""
            )
        ),
    )


def _has_holes(space: ValueSpace, plan: Reparameterization, seed: int, n: int = 64) -> bool:
    """Whether the density is zero (or not finite) at any of ``n`` standard-normal ``z``."""
    rng = np.random.default_rng(seed)
    for z in rng.normal(size=(n, plan.ndim)):
        with np.errstate(all="ignore"):
            if not np.isfinite(plan.logp_dlogp(space, z, safe=True)[0]):
                return True
    return False


def _box_ridge_reason(space: ValueSpace, box: BoxRidgePlan, best: Reparameterization):
    """``box`` with its reason: what ridge, and what the best Laplace map scored."""
    by_index = interval_labels(space)
    named = ", ".join(by_index[int(i)] for i in box.box[0])
    return replace(
        box,
        reason=(
            f"the posterior is a flat ridge in the log of {named}, cut off by their prior "
            f"bounds (Gaussian score of the best Laplace map {best.gaussian_score:.3g}, of "
            f"this map {box.gaussian_score:.3g}): sampled across the ridge whitened and along it "
            "between the bounds its line meets"
        ),
    )
