r"""A funnel between an unknown noise sd and the parameters its few rows inform, mapped away.

An output measured at a few rows with an unknown noise sd σ (a rod's tip temperature at
3 of 14 settings) informs some directions of θ with precision ∝ 1/σ²: where σ is small
the posterior is narrow across them, where it is large only the prior and the other
outputs hold them.  The posterior is a funnel, whose neck a whitening fitted at the
mode cannot follow; NUTS diverges there (a rod: 30 divergences in 4 × 1000 draws under
a GP discrepancy of the other output, at σ half its median).

In the sampling coordinates ``z`` of a plan (``inner``, e.g. the Laplace whitening), let
``t = qᵀz`` be the coordinate along which ``v_σ = ln σ`` moves (``v_σ = v̂_σ + |g| t``),
and ``x`` the others.  For a Gaussian likelihood the precision of ``x`` given ``t`` is

.. math::

    P(r) = A + r B, \qquad r = (\hat\sigma/\sigma)^2 = e^{-2|g|t},

with ``B`` the curvature from the output's rows at ``σ̂`` and ``A`` the rest; both are
measured by differencing the Hessian of ``x`` at ``σ̂`` and at ``σ̂ e^{±τ}`` with the
other parameters held (a third difference checks the ``1/σ²`` form).  With ``H₀ = A + B``
the Hessian at the mode and ``B W = H₀ W Λ`` (``Wᵀ H₀ W = I``),
``P(r) = W⁻ᵀ (I + (r − 1) Λ) W⁻¹``, and the map

.. math::

    z = q\,t + M E\,D(t)\,y_{\perp}, \qquad t = T(y_0),\qquad
    D(t) = \operatorname{diag}\big(1 + \lambda_i f(u)\big)^{-1/2},\quad u = \ln r,

with ``M`` an orthonormal complement of ``q`` and ``E = [W_I, N]``: the eigenvectors
whose ``λ`` is not negligible (the directions the rows inform, whitened at the mode), then
an orthonormal basis of the rest (``λ = 0``: ``inner``'s coordinates, rotated).  The map
narrows the informed directions as σ shrinks, as ``P(r)`` does.  ``f(u) = (eᵘ − 1) σ(2u)``
is ``r − 1`` in the neck and fades to 0 in the mouth: there the width of such a direction
is set by the prior box and the other outputs' curved ridge, not by σ, and widening it as
σ threw NUTS off (rod M1: 58 divergences against 14 without the map).  ``T`` maps a
standard normal to the profile of the log density along ``t`` (``y_⊥ = 0``) by matching
quantiles (:func:`_warped`), which straightens the walls of ``ln σ``'s marginal.  The map
is triangular (``t`` from ``y_0`` alone), so its log-Jacobian is exact,
``ln T'(y_0) − ½ Σ ln(1 + λ_i f(u))`` up to a constant, and the posterior is unchanged.

:func:`funnel_plan` measures every scalar log-transformed parameter (the noise sds,
σ_obs, and any other ``HalfNormal``-type scale) whose ``x``-Hessian has the ``A + r B``
form, keeps the one whose conditional sds (Laplace order) change most over ±2 of its
sds, and wraps ``inner`` when that ratio exceeds :data:`FUNNEL_RATIO`; the plan's
reason names it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from functools import cached_property
from typing import Any, ClassVar

import numpy as np
from scipy import linalg, optimize
from scipy.special import expit

from kohpymc.quantile_warp import spline_through_quantiles, unwarped, warped
from kohpymc.reparameterization import Reparameterization, _gaussian_score, _hessian
from kohpymc.value_space import ValueSpace

__all__ = ["FUNNEL_RATIO", "FunnelPlan", "NoiseFunnel", "funnel_plan"]

#: a funnel is mapped when some conditional sd changes more than this factor between
#: ``t = c − 2s`` and ``c + 2s`` (rod M0: 6.8 for the 3-row temperature's σ)
FUNNEL_RATIO = 3.0

#: largest relative error of the ``A + r B`` form at ``σ̂ e^{−τ}`` for a parameter to count
#: as a noise sd (a Gaussian likelihood's: 1e-12 on the rod)
_FORM_TOL = 0.05

#: steepness of the gate ``σ(k u)`` that fades the narrowing out where σ exceeds its value
#: at the mode (rod M1, 4 × 1000 draws: 58 divergences widening as σ, 10 widening at most
#: twice, 0 gated)
_GATE = 2.0

#: a direction counts as informed by the rows when ``λ`` (its share of the curvature at the
#: mode that comes from them) exceeds this; it is whitened at the mode and narrowed with σ,
#: the others keep ``inner``'s coordinates (rotated)
_INFORMED = 0.05

#: step of ``ln σ`` (in its own units) for the Hessian differences
_TAU = 0.5


@dataclass(frozen=True)
class NoiseFunnel:
    """The triangular map ``y → z`` of the module docstring.

    Attributes
    ----------
    index : int
        Value-space index of ``ln σ``.
    q : ndarray
        Unit direction of ``t`` in ``z``.
    slope : float
        ``|g|``: the change of ``ln σ`` per unit ``t``.
    complement : ndarray
        Shape ``(d, d − 1)``: orthonormal columns orthogonal to ``q``.
    axes : ndarray
        ``E = [W_I, N]``, shape ``(d − 1, d − 1)``, in ``complement``'s coordinates: the
        generalised eigenvectors of ``B`` against the Hessian at the mode whose ``λ``
        exceeds :data:`_INFORMED`, then an orthonormal basis of the rest (``λ = 0``).
    lam : ndarray
        ``λ_i`` in ``[0, 1]``.
    centre, scale : float
        ``c`` and ``s``.
    """

    index: int
    q: np.ndarray
    slope: float
    complement: np.ndarray
    axes: np.ndarray
    lam: np.ndarray
    centre: float = 0.0
    scale: float = 1.0
    warp: Any = None

    def _t(self, y0: float) -> tuple[float, float, float]:
        """``t(y_0)`` and its first two derivatives (affine, or the warp's spline)."""
        return warped(self.warp, self.centre, self.scale, y0)

    def _y0(self, t: float) -> float:
        """The inverse of :meth:`_t`."""
        return unwarped(self.warp, self.centre, self.scale, t)

    @cached_property
    def _unmix(self) -> np.ndarray:
        return np.linalg.inv(self.axes)

    def _stretch(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``a(t) = 1 + λ f(u)`` with ``u = ln r = −2|g|t``, and ``da/dt``.

        ``f(u) = (eᵘ − 1) σ(k u)`` is ``r − 1`` where σ is small (the neck) and fades to
        0 where it is large (the mouth): it narrows, never widens.
        """
        u = -2.0 * self.slope * t
        gate = expit(_GATE * u)
        f = np.expm1(u) * gate
        df = np.exp(u) * gate + np.expm1(u) * _GATE * gate * (1.0 - gate)
        return 1.0 + self.lam * f, self.lam * df * (-2.0 * self.slope)

    def forward(self, y: np.ndarray) -> tuple[np.ndarray, float]:
        """``z(y)`` and ``ln|dz/dy|`` (up to the constant ``ln|det E|``)."""
        t, dt, _ = self._t(y[0])
        a, _ = self._stretch(t)
        x = self.axes @ (y[1:] / np.sqrt(a))
        return self.q * t + self.complement @ x, float(np.log(dt) - 0.5 * np.sum(np.log(a)))

    def inverse(self, z: np.ndarray) -> np.ndarray:
        """``y(z)``."""
        z = np.asarray(z, float)
        t = float(self.q @ z)
        a, _ = self._stretch(t)
        rest = (self._unmix @ (self.complement.T @ z)) * np.sqrt(a)
        return np.concatenate([[self._y0(t)], rest])

    def pull_back(self, y: np.ndarray, grad_z: np.ndarray) -> np.ndarray:
        """Gradient in ``y`` of ``f(z(y)) + ln|dz/dy|`` from ``∇_z f``."""
        t, dt, d2t = self._t(y[0])
        a, da_dt = self._stretch(t)
        h = self.axes.T @ (self.complement.T @ grad_z)
        d_t = self.q @ grad_z + h @ (-0.5 * a**-1.5 * da_dt * y[1:]) - 0.5 * np.sum(da_dt / a)
        return np.concatenate([[dt * d_t + d2t / dt], h / np.sqrt(a)])

    def sd_ratio(self, span: float = 2.0) -> float:
        """Largest ratio of a conditional sd at ``y_0 = +span`` over ``−span`` (Laplace order).

        The conditional precision ``A + r B``, without the gate of the map.
        """
        r_low, r_high = np.exp(
            -2.0 * self.slope * (self.centre + np.array([-span, span]) * self.scale)
        )
        low, high = 1.0 + (r_low - 1.0) * self.lam, 1.0 + (r_high - 1.0) * self.lam
        return float(np.sqrt(np.max(low / high)))


@dataclass(frozen=True)
class FunnelPlan(Reparameterization):
    """``inner``'s plan sampled through a :class:`NoiseFunnel` (``z = funnel(y)``)."""

    #: the funnel's map is numpy only (nutpie calls this plan from Python)
    symbolic: ClassVar[bool] = False
    #: the map undoes the funnel as fitted at the mode, not exactly in its neck: NUTS takes
    #: smaller steps (:data:`kohpymc.sampling.CURVED_TARGET_ACCEPT`).  The three-row rod
    #: (tests/test_funnel.py), 2 × 1000 draws at 8 seeds: at target_accept 0.9, 0–34
    #: divergent transitions per run and ln h's mean down to −5.6 Monte Carlo errors off the
    #: quadrature's; at 0.95, none at all 8 and within 3 errors at 7 (−4.3 at one)
    curved: ClassVar[bool] = True
    inner: Any = None
    funnel: Any = None  # a NoiseFunnel (a default is needed after the base fields)

    def to_value(self, z: np.ndarray) -> np.ndarray:
        """PyMC value-space vector of sampling coordinates ``y``."""
        return self.inner.to_value(self.funnel.forward(np.asarray(z, float))[0])

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector."""
        return self.funnel.inverse(self.inner.from_value(v))

    def laplace_value_sd(self) -> np.ndarray:
        """``inner``'s."""
        return self.inner.laplace_value_sd()

    def logp_dlogp(
        self, space: ValueSpace, z: np.ndarray, *, safe: bool = False
    ) -> tuple[float, np.ndarray]:
        """Log density of ``y`` (exact up to a constant) and its gradient."""
        y = np.asarray(z, float)
        inner_z, logjac = self.funnel.forward(y)
        logp, grad = self.inner.logp_dlogp(space, inner_z, safe=safe)
        return logp + logjac, self.funnel.pull_back(y, grad)


def _direction(plan: Reparameterization, index: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``g = ∂v_i/∂z`` and the ``z`` step that moves ``v_i`` alone by 1 (None when not affine)."""
    d = plan.ndim
    v0 = plan.to_value(np.zeros(d))
    h = 1e-4
    g = np.array([(plan.to_value(h * e)[index] - v0[index]) / h for e in np.eye(d)])
    e = np.zeros(d)
    e[index] = 1.0
    step = plan.from_value(v0 + e) - plan.from_value(v0)
    far = plan.to_value(3.0 * g / (g @ g))[index] - v0[index]
    moved = plan.to_value(step) - v0
    if not (np.isfinite(far) and abs(far - 3.0) < 1e-3 and np.allclose(moved, e, atol=1e-6)):
        return None
    return g, step


def _measure(space: ValueSpace, plan: Reparameterization, index: int) -> NoiseFunnel | None:
    """The funnel of ``v_index`` (``c = 0``, ``s = 1``), or None when ``P ≠ A + r B``."""
    found = _direction(plan, index)
    if found is None:
        return None
    g, step = found
    d = plan.ndim
    slope = float(np.linalg.norm(g))
    q = g / slope
    complement = np.linalg.svd(np.eye(d) - np.outer(q, q))[0][:, : d - 1]

    def across(shift: float) -> np.ndarray:
        hess = _hessian(
            lambda z: plan.logp_dlogp(space, z, safe=True), step * shift, np.full(d, 1e-3)
        )
        return complement.T @ hess @ complement

    at, above, below = across(0.0), across(_TAU), across(-_TAU)
    if not all(np.all(np.isfinite(h)) for h in (at, above, below)):
        return None
    b = (at - above) / (1.0 - np.exp(-2.0 * _TAU))
    predicted = at - b + np.exp(2.0 * _TAU) * b
    if np.linalg.norm(predicted - below) > _FORM_TOL * np.linalg.norm(below):
        return None
    # B = λ (A + B) in the metric of the Hessian at the mode, A + B = C Cᵀ (≈ I in whitened
    # z): λ lies in [0, 1] where both parts are curvatures of log densities near an optimum.
    try:
        chol = np.linalg.cholesky(0.5 * (at + at.T))
    except np.linalg.LinAlgError:
        return None
    inv = np.linalg.inv(chol)
    lam, vecs = np.linalg.eigh(inv @ (0.5 * (b + b.T)) @ inv.T)
    informed = lam > _INFORMED
    if not informed.any():
        return None
    whitened = (inv.T @ vecs)[:, informed]  # Wᵀ H₀ W = I on the informed directions
    rest = linalg.null_space(whitened.T)
    axes = np.column_stack([whitened, rest])
    lam = np.concatenate([np.clip(lam[informed], 0.0, 1.0), np.zeros(rest.shape[1])])
    return NoiseFunnel(index, q, slope, complement, axes, lam)


def _centred(space: ValueSpace, plan: FunnelPlan) -> FunnelPlan | None:
    """``plan`` with ``c`` at the mode of ``y_0``'s profile and ``s`` its ±1.5 half-width."""
    funnel = plan.funnel
    zero = np.zeros(plan.ndim)

    def profile(t: float) -> float:
        trial = replace(plan, funnel=replace(funnel, centre=t, scale=1.0))
        logp, _ = trial.logp_dlogp(space, zero, safe=True)
        return float(logp) if np.isfinite(logp) else -1e300

    best = optimize.minimize_scalar(lambda t: -profile(t), bracket=(-1.0, 1.0))
    centre = float(best.x)
    top = profile(centre)
    half = []
    for sign in (-1.0, 1.0):  # where the profile has dropped by 1.125

        def drop(u, sign=sign):
            return top - profile(centre + sign * u) - 1.125

        hi = 1.0
        while drop(hi) < 0 and hi < 64:
            hi *= 2.0
        if drop(hi) < 0:
            return None
        half.append(optimize.brentq(drop, 1e-9, hi, xtol=1e-4) / 1.5)
    return replace(plan, funnel=replace(funnel, centre=centre, scale=float(np.mean(half))))


def _profile(space: ValueSpace, plan: FunnelPlan) -> Any:
    """Log density of ``plan`` along ``t`` (``y_⊥ = 0``, affine ``t``), as a function of ``t``."""
    affine = replace(plan, funnel=replace(plan.funnel, centre=0.0, scale=1.0, warp=None))
    zero = np.zeros(plan.ndim)

    def profile(t: float) -> float:
        zero[0] = t
        logp, _ = affine.logp_dlogp(space, zero, safe=True)
        return float(logp) if np.isfinite(logp) else -np.inf

    return profile


def _warped(space: ValueSpace, plan: FunnelPlan) -> FunnelPlan:
    """``plan`` with ``t = F⁻¹(Φ(y_0))``, ``F`` the CDF of its profile along ``t``.

    With ``m − 1`` residual degrees of freedom the log density of ``ln σ`` falls as
    ``−S e^{−2u}/2`` towards small σ, a wall whose curvature grows exponentially, and the
    prior's tail bends it at the other end; matching the profile's quantiles to a standard
    normal's straightens both.  A cubic spline through ``Φ(y_k)`` quantiles at
    ``y_k ∈ [−5, 5]``, linear beyond (its own derivative is the log-Jacobian, so the
    density stays exact); ``plan`` unchanged when the spline is not increasing.
    """
    funnel = plan.funnel
    profile = _profile(space, plan)
    top = profile(funnel.centre)
    ends = []
    for sign in (-1.0, 1.0):  # out to where the profile has dropped by 30
        reach = 4.0
        while top - profile(funnel.centre + sign * reach * funnel.scale) < 30 and reach < 64:
            reach *= 2.0
        ends.append(funnel.centre + sign * reach * funnel.scale)
    grid = np.linspace(ends[0], ends[1], 2001)
    dens = np.exp(np.array([profile(t) for t in grid]) - top)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    if not (np.isfinite(cdf[-1]) and cdf[-1] > 0):
        return plan
    warp = spline_through_quantiles(cdf / cdf[-1], grid)
    if warp is None:
        return plan
    return replace(plan, funnel=replace(funnel, warp=warp))


def funnel_plan(space: ValueSpace, inner: Reparameterization) -> FunnelPlan | None:
    """``inner`` wrapped in the strongest noise funnel's map, or None without a funnel.

    Parameters
    ----------
    space : ValueSpace
    inner : Reparameterization
        The plan chosen at the mode (its ``z`` close to standard normal there).

    Returns
    -------
    FunnelPlan or None
        The plan when some scalar log-transformed parameter's conditional sds change by
        more than :data:`FUNNEL_RATIO` over ±2 of its marginal sds.

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> from kohpymc.reparameterization import plan
    >>> with pm.Model() as model:
    ...     a = pm.Normal("a", 0.0, 10.0)
    ...     s = pm.HalfNormal("s", 5.0)
    ...     _ = pm.Normal("y", a, s, observed=[1.0, 1.3, 0.8])
    >>> space = value_space(model)
    >>> funnel_plan(space, plan(space, seed=1)).kind  # doctest: +SKIP
    'noise-funnel-affine'
    """
    if inner.ndim < 2 or inner.mode is None:
        return None
    candidates = []
    for index, transform in enumerate(space.transforms):
        if transform != "log" or not _scalar(space, index):
            continue
        funnel = _measure(space, inner, index)
        if funnel is None or funnel.lam.max() <= 0.0:
            continue
        base = {f.name: getattr(inner, f.name) for f in fields(Reparameterization)}
        wrapped = FunnelPlan(**{**base, "kind": f"noise-funnel-{inner.kind}"},
                             inner=inner, funnel=funnel)  # fmt: skip
        centred = _centred(space, wrapped)
        if centred is not None:
            candidates.append(centred)
    if not candidates:
        return None
    best = max(candidates, key=lambda p: p.funnel.sd_ratio())
    ratio = best.funnel.sd_ratio()
    if ratio <= FUNNEL_RATIO:
        return None
    best = _warped(space, best)
    name = _label(space, best.funnel.index)
    reason = inner.reason.removesuffix(")") + (
        f"; a funnel between {name} and the directions its rows inform (conditional sd "
        f"changes {ratio:.3g}x over ±2 of its sds) sampled with those directions scaled "
        f"by the noise sd)"
    )
    score = _gaussian_score(space, best)
    return replace(best, reason=reason, gaussian_score=score)


def _scalar(space: ValueSpace, index: int) -> bool:
    return any(start == index and size == 1 for _, _, start, size in space.blocks())


def _label(space: ValueSpace, index: int) -> str:
    for _, name, start, size in space.blocks():
        if start <= index < start + size:
            return name.removesuffix("_log__")
    return f"element {index}"
