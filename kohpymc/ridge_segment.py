r"""Sampling along a long straight ridge that a face of the prior box cuts off.

Arrhenius-type models, ``η = A·exp(E/(R T))`` with ``A ~ LogUniform`` and
``E ~ Uniform``, inform ``ln A + E/(R T̄)`` sharply and ``E`` weakly: the posterior is a
ridge that is straight in ``(ln A, E)``, the scales on which the two priors are flat,
and it runs into a face of the box (``A``'s upper bound within two sds of the mode).
Neither Laplace map of :mod:`kohpymc.reparameterization` fits it: PyMC's coordinates
(the logit of ``A`` and of ``E``) and the log-logit ones (``ln E``) bend the ridge, and
the truncation by the face is no Gaussian (scores 3–4; nutpie at defaults: r̂ 1.02–1.04,
3–15 divergences).  The ridge is not flat either (condition number 6·10³, not 10⁶), so
:class:`~kohpymc.reparameterization.BoxRidgePlan` does not apply.

:func:`segment_plan` samples such a posterior as

.. math:: ℓ = ℓ_0 + B\,y + s\,d, \qquad
          s = s_{lo}(y) + (s_{hi}(y) − s_{lo}(y))\,\mathrm{expit}(c + σ τ),

where ``ℓ`` is every bounded parameter on the scale on which its prior is flat (the log
for a log-uniform prior, the parameter's own units for a uniform one: chosen from the
prior's median, :func:`flat_scale_coordinates`), ``d`` is the regression of ``ℓ`` on the
*pivot* (the bounded element whose marginal Laplace sd exceeds its conditional sd the
most), ``B`` whitens the conditional Laplace covariance of the others given the pivot,
and ``s`` runs between the faces of the box the line through ``ℓ₀ + B y`` meets, so
every draw is inside the box and the density has no holes.  ``c`` and ``σ`` centre and
scale the position along the ridge by quadrature at ``y = 0``.  The Jacobian is
``(s_hi − s_lo)·expit'·σ`` times a constant (the segment's ends move with ``y`` along
``d`` only), so the density is exact.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.special import expit

from kohpymc.flat_scale import flat_scale_masks
from kohpymc.prior_bounds import interval_labels
from kohpymc.reparameterization import (
    BoxRidgePlan,
    Coordinates,
    Mode,
    VarianceShare,
    _gaussian_score,
    _laplace,
)
from kohpymc.value_space import ValueSpace

__all__ = [
    "FlatScaleCoordinates",
    "SegmentPlan",
    "flat_scale_coordinates",
    "segment_plan",
    "segment_reason",
]

#: marginal over conditional Laplace sd of the pivot above which the ridge is followed
_RIDGE_RATIO = 10.0

#: Laplace sds from the mode within which a face of the box counts as "in play"
_FACE_SDS = 4.0

#: smallest eigenvalue of the unit-diagonal Laplace precision that the finite-difference
#: Hessian resolves (central differences at 10⁻³ sd: relative errors of order 10⁻⁶);
#: dielectric M4's was −2.2·10⁻⁷ at one refinement of the mode and positive at another,
#: so its plan flipped between affine and ridge segment
_RESOLVED = 1e-6


@dataclass(frozen=True)
class FlatScaleCoordinates(Coordinates):
    r"""Bounded parameters on the scale of their flat prior, with walls at the bounds.

    ``log_scale`` elements are sampled as ``w = ln x`` (``walls=True``, see
    :class:`~kohpymc.reparameterization.Coordinates`); ``own`` elements as ``w = x``
    with zero density outside ``(a, b)``; every other element as ``w = v``.  A plan that
    keeps its draws inside the box (:class:`SegmentPlan`) never meets the walls.

    Examples
    --------
    >>> coords = FlatScaleCoordinates(np.array([True, False]), np.array([1e-9, 1e4]),
    ...                               np.array([1e-3, 6e4]), True,
    ...                               own=np.array([False, True]))
    >>> w = np.array([np.log(1e-5), 2e4])
    >>> bool(np.allclose(coords.from_value(coords.to_value(w)[0]), w))
    True
    """

    own: np.ndarray | None = None

    @property
    def name(self) -> str:
        """``"flat-scale"``."""
        return "flat-scale"

    def to_value(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``v(w)``, ``dv/dw``, ``d log|dv/dw| / dw`` and ``Σ log|dv/dw|`` (NaN outside)."""
        v, dv, dlogjac, logjac = super().to_value(np.asarray(w, float))
        m = self.own
        if m is None or not m.any():
            return v, dv, dlogjac, logjac
        a, b = self.lower[m], self.upper[m]
        x = np.asarray(w, float)[m]
        above, below = x - a, b - x
        with np.errstate(all="ignore"):
            inside = (above > 0) & (below > 0)
            g = (b - a) / (above * below)
            v[m] = np.where(inside, np.log(above) - np.log(below), np.nan)
            dv[m] = np.where(inside, g, np.nan)
            dlogjac[m] = np.where(inside, 1.0 / below - 1.0 / above, np.nan)
            own_logjac = float(np.sum(np.log(g))) if inside.all() else -np.inf
        return v, dv, dlogjac, logjac + own_logjac

    def value_and_log_jacobian(self, w: Any, xp: Any = None) -> tuple[Any, Any]:
        """Numpy only: ``v(w)`` and ``Σ log|dv/dw|`` (no symbolic form)."""
        v, _, _, logjac = self.to_value(np.asarray(w, float))
        return v, logjac

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """``w(v)``: the elementwise maps inverted, then the variance shares."""
        v = np.asarray(v, float)
        w = Coordinates.from_value(replace(self, shares=None), v)
        m = self.own
        if m is not None and m.any():
            w[m] = self.lower[m] + (self.upper[m] - self.lower[m]) * expit(v[m])
        return w if self.shares is None else self.shares.inverse(w)

    @property
    def walled(self) -> np.ndarray:
        """Mask of the elements with walls (log or own units)."""
        own = np.zeros_like(self.log_scale) if self.own is None else self.own
        return self.log_scale | own

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper walls of every element in ``w`` (±inf where none)."""
        lo = np.full(self.log_scale.size, -np.inf)
        hi = np.full(self.log_scale.size, np.inf)
        m, o = self.log_scale, self.walled & ~self.log_scale
        lo[m], hi[m] = np.log(self.lower[m]), np.log(self.upper[m])
        lo[o], hi[o] = self.lower[o], self.upper[o]
        return lo, hi


def flat_scale_coordinates(
    space: ValueSpace, seed: int, shares: VarianceShare | None = None
) -> FlatScaleCoordinates | None:
    """Every bounded parameter of ``space`` on the scale on which its prior is flat.

    The scales are :func:`kohpymc.flat_scale.flat_scale_masks`' (the log for a log-uniform
    prior, the parameter's own units for a uniform one).  None without two interval
    elements (no ridge between box faces).

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.priors import LogUniform, Uniform
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as alone:
    ...     a = LogUniform(1e-9, 1e-3).create("a")
    >>> flat_scale_coordinates(value_space(alone), seed=1) is None
    True
    >>> with pm.Model() as model:
    ...     a = LogUniform(1e-9, 1e-3).create("a")
    ...     e = Uniform(1e4, 6e4).create("e")
    >>> flat_scale_coordinates(value_space(model), seed=1).log_scale.tolist()
    [True, False]
    """
    if space.bounded_intervals().sum() < 2:
        return None
    log_scale, own = flat_scale_masks(space, seed)
    a, b = space.lower, space.upper
    return FlatScaleCoordinates(log_scale, a.copy(), b.copy(), True, shares=shares, own=own)


@dataclass(frozen=True)
class SegmentPlan(BoxRidgePlan):
    """:class:`~kohpymc.reparameterization.BoxRidgePlan` along a ridge that is not flat.

    ``direction`` is the regression of ``ℓ`` on the pivot (entry 1 at ``pivot``), the
    columns of ``basis`` are zero at the pivot, and the last coordinate is
    ``τ = (t − centre)/scale``.  See the module docstring.
    """

    pivot: int = 0
    centre: float = 0.0
    scale: float = 1.0

    def _t(self, z: np.ndarray) -> np.ndarray:
        z = np.array(z, float)
        z[-1] = self.centre + self.scale * z[-1]
        return z

    def to_value(self, z: np.ndarray) -> np.ndarray:
        """PyMC value-space vector of sampling coordinates ``z``."""
        return super().to_value(self._t(z))

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector (ends of the segment clipped)."""
        r = self.coordinates.from_value(np.asarray(v, float)) - self.origin
        s = r[self.pivot]
        rest = np.arange(r.size) != self.pivot
        y = np.linalg.lstsq(self.basis[rest], r[rest] - s * self.direction[rest], rcond=None)[0]
        _, s_lo, _, s_hi, _ = self._segment(y)
        frac = np.clip((s - s_lo) / (s_hi - s_lo), 1e-12, 1 - 1e-12)
        t = np.log(frac) - np.log1p(-frac)
        return np.append(y, (t - self.centre) / self.scale)

    def logp_dlogp(
        self, space: ValueSpace, z: np.ndarray, *, safe: bool = False
    ) -> tuple[float, np.ndarray]:
        """Log density of ``z`` (exact up to a constant) and its gradient."""
        logp, grad = super().logp_dlogp(space, self._t(z), safe=safe)
        grad[-1] *= self.scale
        return logp, grad


def _resolved(chol: np.ndarray) -> bool:
    """Whether every direction of the Laplace fit is resolved.

    Every eigenvalue of the precision ``(L Lᵀ)⁻¹``, scaled to unit diagonal, above
    ``_RESOLVED`` times its largest (a flatter direction is finite-difference noise).
    """
    inverse = np.linalg.inv(chol)
    precision = inverse.T @ inverse
    d = np.sqrt(np.diag(precision))
    eig = np.linalg.eigvalsh(precision / np.outer(d, d))
    return bool(eig.min() > _RESOLVED * eig.max())


def _pivot(cov: np.ndarray, walled: np.ndarray) -> int | None:
    """The walled element whose marginal sd exceeds its conditional sd the most (> ratio)."""
    precision = np.linalg.inv(cov)
    ratio = np.where(walled, np.sqrt(np.diag(cov) * np.diag(precision)), 0.0)
    pivot = int(np.argmax(ratio))
    return pivot if ratio[pivot] > _RIDGE_RATIO else None


def _face_in_play(mean: np.ndarray, sd: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether a wall lies within ``_FACE_SDS`` Laplace sds of the mode."""
    with np.errstate(invalid="ignore"):
        near = (mean - _FACE_SDS * sd < lo) | (mean + _FACE_SDS * sd > hi)
    return bool(np.any(near))


def _centre_and_scale(space: ValueSpace, plan: SegmentPlan) -> tuple[float, float]:
    """Mean and sd of ``t`` at ``y = 0`` by quadrature on ``t ∈ [−30, 30]``.

    Where the sd comes out below ``_RESOLVED_SPACINGS`` grid spacings, the quadrature is
    repeated on a grid of the same size around the first mean, ten spacings of the first
    either side: a peak narrower than the grid is otherwise weighted by one or two points
    (Steinhart–Hart with a GP discrepancy: sd 0.014 on a grid of spacing 0.25, where a
    finer grid gives ~0.1, so that ``τ`` lost its scale: drops of 0.00–0.01 at ±1.5).  A
    wider peak keeps the first grid's moments (the Arrhenius ridge's sd, 0.47, moves to 0.45).
    """
    t = np.linspace(-30.0, 30.0, 241)
    mean, sd = _moments(space, plan, t)
    spacing = t[1] - t[0]
    if sd < _RESOLVED_SPACINGS * spacing:
        mean, sd = _moments(space, plan, np.linspace(mean - 10 * spacing, mean + 10 * spacing, 241))
    return mean, max(sd, 1e-3)


#: a quadrature sd below this many grid spacings is refined (:func:`_centre_and_scale`)
_RESOLVED_SPACINGS = 1.0


def _moments(space: ValueSpace, plan: SegmentPlan, t: np.ndarray) -> tuple[float, float]:
    """Mean and sd of ``t`` at ``y = 0`` on the grid ``t`` (0 and 1 without density)."""
    logp = np.empty(t.size)
    zero = np.zeros(plan.ndim)
    for i, ti in enumerate(t):
        zero[-1] = ti
        with np.errstate(all="ignore"):
            logp[i] = plan.logp_dlogp(space, zero, safe=True)[0]
    if not np.any(np.isfinite(logp)):
        return 0.0, 1.0
    logp = np.where(np.isfinite(logp), logp, -np.inf)
    weight = np.exp(logp - logp.max())
    weight /= weight.sum()
    mean = float(weight @ t)
    return mean, float(np.sqrt(weight @ (t - mean) ** 2))


#: the segment is declined where, ``_STRAIGHT_SDS`` Laplace sds of the pivot either side of
#: the mode, the conditional mode of ``y`` lies more than ``_STRAIGHT_MISS`` above the log
#: density on the line (``½ r²`` for a line ``r`` conditional sds off a straight ridge)
_STRAIGHT_MISS = 2.0
_STRAIGHT_SDS = 2.0


def _tau_at(plan: SegmentPlan, position: float) -> float | None:
    """``τ`` of the point at ``y = 0`` whose pivot lies at ``position`` (None outside)."""
    _, s_lo, _, s_hi, _ = plan._segment(np.zeros(plan.ndim - 1))
    frac = (position - s_lo) / (s_hi - s_lo)
    if not 0.0 < frac < 1.0:
        return None
    return float((np.log(frac) - np.log1p(-frac) - plan.centre) / plan.scale)


def _straight(space: ValueSpace, plan: SegmentPlan, mode_pivot: float, sd_pivot: float) -> bool:
    """Whether the segment's line follows the ridge ``_STRAIGHT_SDS`` pivot sds either side.

    The segment assumes a straight ridge: its line is the ridge's tangent at the mode.
    Where the ridge curves away the draws leave the line by tens of its sds and NUTS
    diverges (Steinhart–Hart M3: at ``τ = −3`` the conditional mode of ``y`` lay 11
    conditional sds off the line, the log density there 55.6 above the line's; 39
    divergences in 2 × 1000 draws, r̂ 1.05).  Checked at the pivot's mode ± ``_STRAIGHT_SDS``
    of its Laplace sds, not at fixed ``τ``: ``τ``'s scale is measured on the line, which
    is narrow where the line leaves a curved ridge.  A side beyond a face is not checked.
    """
    from kohpymc.bends import _conditional_mode

    tau = plan.ndim - 1
    for sign in (-1.0, 1.0):
        at = _tau_at(plan, mode_pivot + sign * _STRAIGHT_SDS * sd_pivot)
        if at is None:
            continue
        line = np.zeros(plan.ndim)
        line[tau] = at
        found = _conditional_mode(space, plan, tau, at)
        if found is None:
            return False
        found[tau] = at
        with np.errstate(all="ignore"):
            on_line = plan.logp_dlogp(space, line, safe=True)[0]
            off_line = plan.logp_dlogp(space, found, safe=True)[0]
        if not np.isfinite(on_line) or off_line - on_line > _STRAIGHT_MISS:
            return False
    return True


def segment_plan(
    space: ValueSpace, mode: Mode, seed: int, shares: VarianceShare | None = None
) -> SegmentPlan | None:
    """A :class:`SegmentPlan` when the posterior is a long ridge that a face cuts off.

    None unless, in :func:`flat_scale_coordinates`, the Laplace covariance at the mode is
    positive definite with no direction flatter than the finite-difference Hessian resolves
    (a ridge that flat is :class:`~kohpymc.reparameterization.BoxRidgePlan`'s), a bounded
    element's marginal sd exceeds its conditional sd more than ten times (a ridge), and a
    wall lies within four Laplace sds of the mode; None too where the ridge curves away from
    the line (:func:`_straight`).

    Examples
    --------
    >>> found = segment_plan(space, mode, seed=1)  # doctest: +SKIP
    >>> found.kind  # doctest: +SKIP
    'ridge-segment-flat-scale'
    """
    coords = flat_scale_coordinates(space, seed, shares)
    if coords is None:
        return None
    start = coords.from_value(mode.value)
    if not np.all(np.isfinite(start)):
        return None
    ell0, chol = _laplace(space, coords, start)
    if chol is None or not _resolved(chol):
        return None
    cov = chol @ chol.T
    walled = coords.walled
    pivot = _pivot(cov, walled)
    lo, hi = coords.bounds()
    if pivot is None or not _face_in_play(ell0, np.sqrt(np.diag(cov)), lo, hi):
        return None
    direction = cov[:, pivot] / cov[pivot, pivot]
    rest = np.flatnonzero(np.arange(ell0.size) != pivot)
    conditional = cov[np.ix_(rest, rest)] - np.outer(direction[rest], cov[pivot, rest])
    try:
        factor = np.linalg.cholesky(0.5 * (conditional + conditional.T))
    except np.linalg.LinAlgError:
        return None
    basis = np.zeros((ell0.size, rest.size))
    basis[rest] = factor
    index = np.flatnonzero(walled & (direction != 0))
    plan = SegmentPlan(
        "ridge-segment-flat-scale", np.zeros(ell0.size), np.eye(ell0.size), coords, "", mode,
        origin=ell0 - ell0[pivot] * direction, basis=basis,
        precision_sqrt=np.zeros(rest.size), direction=direction,
        box=(index, lo[index], hi[index]), pivot=pivot,
    )  # fmt: skip
    centre, scale = _centre_and_scale(space, plan)
    plan = replace(plan, centre=centre, scale=scale)
    if not np.isfinite(plan.logp_dlogp(space, np.zeros(plan.ndim), safe=True)[0]):
        return None
    if not _straight(space, plan, float(ell0[pivot]), float(np.sqrt(cov[pivot, pivot]))):
        return None
    return replace(plan, gaussian_score=_gaussian_score(space, plan))


def segment_reason(space: ValueSpace, plan: SegmentPlan, best: Any) -> SegmentPlan:
    """``plan`` with its reason: the pivot, the scales, and the scores."""
    by_index = interval_labels(space)
    logs = ", ".join(by_index[int(i)] for i in np.flatnonzero(plan.coordinates.log_scale))
    return replace(
        plan,
        reason=(
            f"the posterior is a long ridge led by {by_index[int(plan.pivot)]} that a face of "
            f"the prior box cuts off (Gaussian score of the best Laplace map "
            f"{best.gaussian_score:.3g}, of this map {plan.gaussian_score:.3g}): sampled "
            "along it between the faces its line meets and across it whitened, with the "
            "bounded parameters on the scale of their flat prior"
            + (f" ({logs} on the log scale)" if logs else "")
        ),
    )
