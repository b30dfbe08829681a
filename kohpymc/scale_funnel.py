r"""A funnel between a discrepancy's scale and the rest, followed by conditional modes and scales.

A discrepancy's variance parameters (an input-dependent log-variance, a GP's amplitude)
set how much of the data's shape the discrepancy may take up, and with it how far the
physics parameters may move: where the discrepancy variance is large the physics is held
less and its conditional modes move.  Steinhart–Hart under M3 (linear mean, log-linear
variance, σ_obs unknown): over ±2 marginal sds of the log-variance's intercept the others'
conditional sds change 2.3× and their modes move 2.4 conditional sds; under M4 past the GP
amplitude's 90 % quantile one whitened physics axis has sd 2.9 and mean −2.8 (1.3 and 0.2
below).  The noise-funnel map (:mod:`kohpymc.funnel`) needs the noise sd's own form
``A + r B``, ``r = (σ̂/σ)²``; a plan fitted at the mode follows neither.

In the sampling coordinates ``z`` of a plan (``inner``), let ``t = qᵀz`` run along the
direction that moves the scale's value-space coordinate ``v_i`` at the mode, and
``x = Mᵀz`` the rest (``M`` an orthonormal complement of ``q``).  The map

.. math::

    z = q\,t + M\,(m(t) + L(t)\,y_{\perp}),\qquad t = T(y_0),

has ``m(t)`` a cubic spline through the conditional modes of ``x`` at nodes of ``t``
marched outwards from the mode (midpoints added where the spline misses the mode),
``L(t)`` one through the Cholesky factors of the conditional Laplace covariances there
(log diagonal and lower entries), both held at their outer nodes' values beyond them
(``m`` continued linearly), and ``T`` the quantile warp (:mod:`kohpymc.quantile_warp`)
of the Laplace marginal of ``t``, ``exp(log p(t, m(t))) det L(t)``.  The map is
triangular, so its log-Jacobian ``ln T'(y_0) + ln det L(t)`` is exact and the posterior
unchanged.

:func:`scale_funnel_plan` measures every element of the scale parameters it is given
(:meth:`kohpymc.discrepancy.base.Discrepancy.scale_parameters`: M3's ``delta_logvar``),
and wraps ``inner`` in the map of the one that scores closest to a Gaussian among those
whose conditional sds change more than :data:`SCALE_FUNNEL_RATIO` or whose modes move
more than :data:`SCALE_FUNNEL_SHIFT` conditional sds over ``t = ±2`` of its marginal sds,
when it scores closer than ``inner``.  Steinhart–Hart M3 at the defaults (4 × 1000
draws, seeds 2 and 3): 3 and 31 divergent transitions, bulk ESS 957 and 562, 31 leapfrog
steps per draw before; 7 and 10, 2676 and 2764, 13–14 steps with the map.  Not offered for
the GP's amplitude: on Steinhart–Hart M4 the conditional modes jump 22 conditional sds
between two nodes where the GP takes up the physics' shape, which no Laplace factor
follows (97 divergent transitions before, 49–226 with the map, by the inner plan).  On the
ridge curve with its pivot warped (:mod:`kohpymc.ridge_curve`) the amplitude's funnel still
widens B 20 conditional sds at η ≈ 12, where most of the remaining divergences sit, but
this map over it diverged more at the defaults (seed 3: 46 against 21 in the first run, 10
against 13 after the second, bulk ESS 804 against 958, 53 leapfrog steps against 32).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from scipy import optimize
from scipy.interpolate import CubicSpline
from scipy.linalg import solve_triangular
from scipy.special import logit

from kohpymc.funnel import FunnelPlan, _label
from kohpymc.quantile_warp import spline_through_quantiles, unwarped, warped
from kohpymc.reparameterization import (
    Reparameterization,
    _gaussian_score,
    _hessian,
    _inverse_cholesky,
)
from kohpymc.ridge_curve import RidgeCurvePlan, _pivot_warp, lower_factor
from kohpymc.value_space import ValueSpace

__all__ = ["SCALE_FUNNEL_RATIO", "SCALE_FUNNEL_SHIFT", "ScaleFunnel", "scale_funnel_plan"]

#: a scale funnel is mapped when a conditional sd of the rest changes more than this factor
#: between ``t = −2`` and ``+2`` marginal sds of ``t`` ...
SCALE_FUNNEL_RATIO = 3.0
#: ... or a conditional mode moves more than this many conditional sds between them
SCALE_FUNNEL_SHIFT = 1.0

#: nodes of ``t`` (in marginal sds of ``t`` around the mode) where modes and factors are
#: found, marched outwards while the profile has dropped less than :data:`_FAR_DROP`
_NODES = np.array([0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.5, 8.0, 10.5, 14.0, 18.0, 24.0])
_FAR_DROP = 30.0

#: L-BFGS settings of the conditional modes
_MODE_OPTIONS = {"maxiter": 3000, "ftol": 1e-14, "gtol": 1e-9}


@dataclass(frozen=True)
class ScaleFunnel:
    """The triangular map ``y → z`` of the module docstring.

    Attributes
    ----------
    index : int
        Value-space index of the scale's log.
    q, complement : ndarray
        Unit direction of ``t`` in ``z`` and an orthonormal complement, ``(d, d − 1)``.
    nodes : ndarray
        The ``t`` of the splines, increasing.
    curve, factor : CubicSpline
        ``m(t)`` and the entries of ``L(t)`` (log diagonal, then the lower triangle).
    warp : CubicSpline or None
        ``T``; with None ``t = centre + scale · y_0``.
    """

    index: int
    q: np.ndarray
    complement: np.ndarray
    nodes: np.ndarray
    curve: Any
    factor: Any
    warp: Any = None
    centre: float = 0.0
    scale: float = 1.0

    def _t(self, y0: float) -> tuple[float, float, float]:
        return warped(self.warp, self.centre, self.scale, y0)

    def _parts(self, t: float):
        """``m(t)``, ``m'(t)``, ``L(t)``, ``L'(t)``, ``ln det L(t)`` and its derivative."""
        lo, hi = float(self.nodes[0]), float(self.nodes[-1])
        edge = min(max(t, lo), hi)
        inside = lo < t < hi
        n = self.complement.shape[1]
        slope = self.curve(edge, 1)
        m = self.curve(edge) + (0.0 if inside else slope * (t - edge))
        entries = self.factor(edge)
        dentries = self.factor(edge, 1) if inside else np.zeros_like(entries)
        return (m, slope, *lower_factor(entries, dentries, n))

    def forward(self, y: np.ndarray) -> tuple[np.ndarray, float]:
        """``z(y)`` and ``ln|dz/dy|``."""
        y = np.asarray(y, float)
        t, dt, _ = self._t(float(y[0]))
        m, _, chol, _, logdet, _ = self._parts(t)
        x = m + chol @ y[1:]
        return self.q * t + self.complement @ x, float(np.log(dt) + logdet)

    def inverse(self, z: np.ndarray) -> np.ndarray:
        """``y(z)``."""
        z = np.asarray(z, float)
        t = float(self.q @ z)
        m, _, chol, _, _, _ = self._parts(t)
        rest = solve_triangular(chol, self.complement.T @ z - m, lower=True)
        return np.concatenate([[unwarped(self.warp, self.centre, self.scale, t)], rest])

    def pull_back(self, y: np.ndarray, grad_z: np.ndarray) -> np.ndarray:
        """Gradient in ``y`` of ``f(z(y)) + ln|dz/dy|`` from ``∇_z f``."""
        y = np.asarray(y, float)
        t, dt, d2t = self._t(float(y[0]))
        _, dm, chol, dchol, _, dlogdet = self._parts(t)
        gx = self.complement.T @ grad_z
        d_t = float(self.q @ grad_z + gx @ (dm + dchol @ y[1:])) + dlogdet
        return np.concatenate([[dt * d_t + d2t / dt], chol.T @ gx])

    def changes(self, span: float = 2.0) -> tuple[float, float]:
        """Largest conditional-sd ratio and mode shift (in conditional sds) over ``t = ±span``.

        ``span`` in marginal sds of ``t`` (``scale``), around ``centre``.
        """
        a, b = self.centre - span * self.scale, self.centre + span * self.scale
        ma, _, la, _, _, _ = self._parts(a)
        mb, _, lb, _, _, _ = self._parts(b)
        sv = np.linalg.svd(solve_triangular(la, lb, lower=True), compute_uv=False)
        ratio = float(max(sv.max(), 1.0 / sv.min()))
        shift = np.concatenate(
            [solve_triangular(la, mb - ma, lower=True), solve_triangular(lb, mb - ma, lower=True)]
        )
        return ratio, float(np.abs(shift).max())


def _direction(plan: Reparameterization, index: int) -> np.ndarray | None:
    """``∂v_index/∂z`` at ``z = 0`` (None when zero or not finite)."""
    d = plan.ndim
    h = 1e-4
    g = np.array(
        [(plan.to_value(h * e)[index] - plan.to_value(-h * e)[index]) / (2 * h) for e in np.eye(d)]
    )
    if not (np.all(np.isfinite(g)) and np.linalg.norm(g) > 0):
        return None
    return g


class _Slice:
    """The inner plan's log density with ``t`` held, as a function of ``x``."""

    def __init__(self, space: ValueSpace, plan: Reparameterization, q, complement) -> None:
        self.space, self.plan, self.q, self.complement = space, plan, q, complement

    def logp(self, t: float, x: np.ndarray) -> tuple[float, np.ndarray]:
        with np.errstate(all="ignore"):
            logp, grad = self.plan.logp_dlogp(
                self.space, self.q * t + self.complement @ x, safe=True
            )
        return float(logp), self.complement.T @ grad

    def mode(self, t: float, guess: np.ndarray, chol: np.ndarray) -> tuple[np.ndarray, float]:
        """Conditional mode of ``x`` (L-BFGS whitened by ``chol``) and its log density."""

        def objective(u):
            logp, grad = self.logp(t, guess + chol @ u)
            if not np.isfinite(logp) or not np.all(np.isfinite(grad)):
                return np.inf, np.zeros(u.size)
            return -logp, -(chol.T @ grad)

        result = optimize.minimize(
            objective, np.zeros(guess.size), jac=True, method="L-BFGS-B", options=_MODE_OPTIONS
        )
        x = guess + chol @ result.x
        return x, self.logp(t, x)[0]

    def factor(self, t: float, x: np.ndarray, chol: np.ndarray) -> np.ndarray | None:
        """Cholesky factor of the conditional Laplace covariance at ``x`` (None if not PD)."""
        n = x.size

        def whitened(u):
            logp, grad = self.logp(t, x + chol @ u)
            return logp, chol.T @ grad

        inner = _inverse_cholesky(_hessian(whitened, np.zeros(n), np.full(n, 1e-3)))
        return None if inner is None else chol @ inner


def _march(cond: _Slice, scale: float, n: int):
    """Nodes of ``t``, conditional modes, log densities and factors, marched from ``t = 0``.

    Each side goes outwards through :data:`_NODES` (times ``scale``) while the log
    density at the last mode is less than :data:`_FAR_DROP` below the mode's; each search
    starts from the linear extrapolation of the two previous modes, whitened by the
    previous node's factor.  None when a node has no finite mode or no positive-definite
    conditional Hessian.
    """
    start, top = cond.mode(0.0, np.zeros(n), np.eye(n))
    first = cond.factor(0.0, start, np.eye(n)) if np.isfinite(top) else None
    if first is None:
        return None
    found = {0.0: (start, top, first)}
    for sign in (1.0, -1.0):
        previous, chol = [(0.0, start)], first
        for t in sign * scale * _NODES:
            guess = previous[-1][1]
            if len(previous) > 1:
                (ta, xa), (tb, xb) = previous[-2], previous[-1]
                guess = xb + (xb - xa) * (t - tb) / (tb - ta)
            x, logp = cond.mode(float(t), guess, chol)
            factor = cond.factor(float(t), x, chol) if np.isfinite(logp) else None
            if factor is None:  # the side ends at its last node with a factor
                break
            found[float(t)], chol = (x, logp, factor), factor
            previous.append((float(t), x))
            if top - logp > _FAR_DROP:
                break
    if len(found) < 5:
        return None
    return _refined(cond, found, top)


#: a midpoint becomes a node where the log density at the splines' value lies more than
#: this below the conditional mode there; at most ``_ROUNDS`` rounds
_MISS = 0.25
_ROUNDS = 4


def _refined(cond: _Slice, found: dict, top: float):
    """Nodes and their (mode, log density, factor), midpoints added where the splines miss.

    Only between nodes within :data:`_FAR_DROP` of ``top``; the midpoint's mode starts from
    the splines' value, whitened by the nearer node's factor (the modes may turn within one
    interval: Steinhart–Hart under a GP, where the amplitude reaches the physics' shape,
    they move 22 conditional sds between two nodes).
    """
    for _ in range(_ROUNDS):
        nodes = np.array(sorted(found))
        modes = CubicSpline(nodes, np.array([found[float(t)][0] for t in nodes]), axis=0)
        added = False
        for a, b in zip(nodes[:-1], nodes[1:], strict=True):
            if min(top - found[float(a)][1], top - found[float(b)][1]) > _FAR_DROP:
                continue
            mid = float(0.5 * (a + b))
            guess = modes(mid)
            x, logp = cond.mode(mid, guess, found[float(a)][2])
            factor = cond.factor(mid, x, found[float(a)][2]) if np.isfinite(logp) else None
            if factor is None or logp - cond.logp(mid, guess)[0] <= _MISS:
                continue
            found[mid], added = (x, logp, factor), True
        if not added:
            break
    nodes = np.array(sorted(found))
    return nodes, [found[float(t)] for t in nodes]


def _fitted(cond: _Slice, index: int, scale: float) -> ScaleFunnel | None:
    """The :class:`ScaleFunnel` along ``cond``'s ``t`` (None where a node fails)."""
    n = cond.complement.shape[1]
    marched = _march(cond, scale, n)
    if marched is None:
        return None
    nodes, rows = marched
    lower = np.tril_indices(n, -1)
    modes = np.array([x for x, _, _ in rows])
    entries = np.array([np.concatenate([np.log(np.diag(f)), f[lower]]) for _, _, f in rows])
    marginal = np.array([logp + np.log(np.diag(f)).sum() for _, logp, f in rows])
    funnel = ScaleFunnel(
        index, cond.q, cond.complement, nodes,
        CubicSpline(nodes, modes, axis=0), CubicSpline(nodes, entries, axis=0),
    )  # fmt: skip
    return _warped(funnel, nodes, marginal)


def _warped(funnel: ScaleFunnel, nodes: np.ndarray, marginal: np.ndarray) -> ScaleFunnel:
    """``funnel`` with ``t`` warped to the quantiles of its Laplace marginal.

    The marginal's log density is a cubic spline through its values at the nodes, linear
    beyond them out to a drop of 30 on each side.  Without a warp (the spline not
    increasing) ``t`` is centred on the marginal's mode, scaled by its ±1.5 half-width.
    """
    top = float(marginal.max())
    spline = CubicSpline(nodes, marginal - top)
    grid = np.linspace(nodes[0], nodes[-1], 4001)
    dens = np.exp(spline(grid))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    mean = float(np.sum(grid * dens) / np.sum(dens))
    sd = float(np.sqrt(np.sum((grid - mean) ** 2 * dens) / np.sum(dens)))
    warp = spline_through_quantiles(cdf / cdf[-1], grid) if cdf[-1] > 0 else None
    return replace(funnel, warp=warp, centre=mean, scale=sd)


def scale_funnel_plan(
    space: ValueSpace, inner: Reparameterization, names: Sequence[str] = ()
) -> FunnelPlan | None:
    """``inner`` wrapped in the strongest scale funnel's map, or None without one.

    Parameters
    ----------
    space : ValueSpace
    inner : Reparameterization
        The plan chosen at the mode (any map ``z → v``, its ``z`` close to standard
        normal there).  A curved ridge's plan whose pivot is not warped is measured with
        its pivot warped to the quantiles of its Laplace marginal
        (:func:`_with_warped_pivot`).
    names : sequence of str
        The scale parameters (a discrepancy's
        :meth:`~kohpymc.discrepancy.base.Discrepancy.scale_parameters`); every element of
        each is measured.  Names not in the model are skipped.

    Returns
    -------
    FunnelPlan or None
        ``inner`` sampled through a :class:`ScaleFunnel`, when some scalar
        log-transformed parameter's conditional sds change by more than
        :data:`SCALE_FUNNEL_RATIO` or its conditional modes move more than
        :data:`SCALE_FUNNEL_SHIFT` sds over ±2 of its marginal sds, and the map scores
        closer to a Gaussian than ``inner``.

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> from kohpymc.reparameterization import plan
    >>> x = np.linspace(1.0, 3.0, 3)
    >>> with pm.Model() as model:
    ...     a = pm.Uniform("a", -50.0, 50.0)
    ...     b = pm.Uniform("b", -50.0, 50.0)
    ...     tau = pm.HalfNormal("tau", 1.0)
    ...     sd = pm.math.sqrt(0.05**2 + tau**2 * x**2)
    ...     _ = pm.Normal("y", a + b * x, sd, observed=[3.1, 5.0, 6.6])
    >>> space = value_space(model)
    >>> scale_funnel_plan(space, plan(space, seed=1), ["tau"]).kind  # doctest: +SKIP
    'scale-funnel-affine'
    """
    indices = _scales(space, names)
    if inner.ndim < 2 or inner.mode is None or not indices:
        return None
    original, inner = inner, _with_warped_pivot(space, inner)
    found = []
    for index in indices:
        g = _direction(inner, index)
        if g is None:
            continue
        q = g / np.linalg.norm(g)
        complement = np.linalg.svd(np.eye(inner.ndim) - np.outer(q, q))[0][:, : inner.ndim - 1]
        funnel = _fitted(_Slice(space, inner, q, complement), index, 1.0)
        if funnel is None:
            continue
        ratio, shift = funnel.changes()
        if ratio > SCALE_FUNNEL_RATIO or shift > SCALE_FUNNEL_SHIFT:
            base = {f.name: getattr(inner, f.name) for f in fields(Reparameterization)}
            wrapped = FunnelPlan(**{**base, "kind": f"scale-funnel-{inner.kind}"},
                                 inner=inner, funnel=funnel)  # fmt: skip
            found.append((_gaussian_score(space, wrapped), wrapped, ratio, shift))
    if not found:
        return None
    score, best, ratio, shift = min(found, key=lambda item: item[0])
    if not score < original.gaussian_score:
        return None
    name = _label(space, best.funnel.index)
    reason = inner.reason.removesuffix(")") + (
        f"; a funnel between {name} and the rest (conditional sd changes {ratio:.3g}x, "
        f"conditional modes move {shift:.3g} sds over ±2 of its sds) followed by the "
        f"conditional modes and scales)"
    )
    return replace(best, reason=reason, gaussian_score=score)


def _scales(space: ValueSpace, names: Sequence[str]) -> list[int]:
    """Value-space indices of every element of the parameters ``names`` in ``space``."""
    blocks = space.blocks()
    return [i for rv, _, start, size in blocks if rv in names for i in range(start, start + size)]


def _with_warped_pivot(space: ValueSpace, inner: Reparameterization) -> Reparameterization:
    """A curved ridge's plan with its pivot warped to its Laplace marginal's quantiles.

    The marginal at the nodes is the plan's log density at ``y = 0`` (the profile plus
    the log determinant of the conditional factor).  Along Steinhart–Hart's ridge under
    an input-dependent discrepancy the pivot's marginal has a wall where C falls below
    −1.3·10⁻⁷ and the variances take up the misfit (its whitened coordinate: 0.1 %
    quantile −1.353, 0.05 % −1.356); the funnel of the variances is measured and followed
    along the straightened pivot.  ``inner`` unchanged when it is not such a plan or the
    warp scores no closer to a Gaussian.
    """
    if not isinstance(inner, RidgeCurvePlan) or inner.warp is not None:
        return inner
    warped_plan = _warped_pivot(space, inner, inner.reason)
    if warped_plan is None or not warped_plan.gaussian_score < inner.gaussian_score:
        return inner
    return warped_plan


def _warped_pivot(space: ValueSpace, inner: RidgeCurvePlan, reason: str) -> RidgeCurvePlan | None:
    """:func:`_with_warped_pivot`'s plan (None when the warp is not increasing)."""
    marginal = []
    for s in inner.nodes:
        z = np.zeros(inner.ndim)
        z[0] = (logit(s) - inner.centre) / inner.scale
        marginal.append(inner.logp_dlogp(space, z, safe=True)[0])
    warp = _pivot_warp(inner.nodes, np.array(marginal))
    if warp is None:
        return None
    reason = reason.removesuffix(")") + "; its pivot warped to its marginal's quantiles)"
    warped_plan = replace(inner, kind=f"{inner.kind}-warped", warp=warp, reason=reason)
    return replace(warped_plan, gaussian_score=_gaussian_score(space, warped_plan))
