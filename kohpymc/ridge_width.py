r"""A ridge whose width changes along it: the other coordinates scaled with the bent axes.

A :class:`~kohpymc.bends.CurveBend` moves the *centre* of the other sampling coordinates
along a bent axis ``z_k``; their conditional *width* it leaves as whitened at the mode.
Where the ridge narrows (dielectric M2's ε_∞ axis of its bent ridge curve: beyond
``z = −3.25`` one other coordinate's conditional precision jumps from 1 to 120–160),
NUTS's step, adapted to the bulk, is unstable.  :class:`Widths` scales those coordinates

.. math:: z'_r = z_r \exp\Big(\sum_{k \in K} g_{k,r}(z_k)\Big), \qquad r \notin K,

with ``g_{k,r}`` a spline (zero at 0, clamped flat at and beyond the outer nodes) through
``½ ln(H_rr(0) / H_rr(t))`` at the bent path's nodes ``t``: ``H_rr(t)`` is the
conditional precision of ``z_r`` on the path (the diagonal of the Hessian of ``−log p``
at the others' conditional mode with ``z_k = t``).  The map is triangular (the bent axes
are not scaled), ``log|∂z'/∂z| = Σ_r Σ_k g_{k,r}(z_k)`` is added exactly, and it is the
identity at the mode, where the whitening was fitted.  :func:`widen_plan` keeps it when
it brings the drops across the ridge at ``z_k = ±1.5, ±3`` at least
:data:`WIDTH_GAIN` closer to a Gaussian's (:func:`transverse_error`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline

from kohpymc.reparameterization import _GAUSSIAN_DROP, Reparameterization, _hessian
from kohpymc.value_space import ValueSpace

__all__ = ["WIDTH_GAIN", "Widths", "transverse_error", "widen_plan"]

#: the widths are kept when they lower :func:`transverse_error` by at least this share
WIDTH_GAIN = 0.1

#: where along a bent axis :func:`transverse_error` looks across the ridge (in sds)
_ALONG = (-3.0, -1.5, 1.5, 3.0)


@dataclass(frozen=True)
class Widths:
    r"""``z'_r = z_r·exp(Σ_k g_{k,r}(z_k))`` for ``r ∉ K`` (see the module docstring).

    Attributes
    ----------
    axes : tuple of int
        The bent axes ``K`` (not scaled).
    nodes : ndarray
        Where the splines are fitted (they hold 0 at ``t = 0``).
    logs : ndarray
        ``(|K|, len(nodes), n)``: ``g_{k,r}`` at the nodes, zero on the bent axes.

    Examples
    --------
    >>> nodes = np.array([-1.0, 0.0, 1.0])
    >>> logs = np.zeros((1, 3, 2))
    >>> logs[0, :, 1] = [np.log(0.5), 0.0, 0.0]
    >>> widths = Widths((0,), nodes, logs)
    >>> widths.forward(np.array([-1.0, 2.0]))
    array([-1.,  1.])
    >>> float(widths.log_jacobian(np.array([-1.0, 2.0]))[0])  # ln 0.5
    -0.6931471805599453
    """

    axes: tuple[int, ...]
    nodes: np.ndarray
    logs: np.ndarray

    @cached_property
    def _splines(self) -> list[CubicSpline]:
        return [CubicSpline(self.nodes, g, axis=0, bc_type="clamped") for g in self.logs]

    def _log_scales(self, z: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """``G = Σ_k g_k(z_k)`` and each ``g_k'(z_k)`` (zero beyond the outer nodes)."""
        total, slopes = np.zeros(z.size), []
        lo, hi = self.nodes[0], self.nodes[-1]
        for spline, k in zip(self._splines, self.axes, strict=True):
            t = float(z[k])
            inside = lo < t < hi
            total += spline(min(max(t, lo), hi))
            slopes.append(spline(t, 1) if inside else np.zeros(z.size))
        return total, slopes

    def forward(self, z: np.ndarray) -> np.ndarray:
        """``z'`` from ``z``."""
        z = np.asarray(z, float)
        return z * np.exp(self._log_scales(z)[0])

    def inverse(self, w: np.ndarray) -> np.ndarray:
        """``z`` from ``z'`` (the bent axes are not scaled)."""
        w = np.asarray(w, float)
        return w * np.exp(-self._log_scales(w)[0])

    def log_jacobian(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """``log|∂z'/∂z|`` and its gradient."""
        z = np.asarray(z, float)
        total, slopes = self._log_scales(z)
        grad = np.zeros(z.size)
        for slope, k in zip(slopes, self.axes, strict=True):
            grad[k] += slope.sum()
        return float(total.sum()), grad

    def pull_back(self, z: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``z`` from the gradient at :meth:`forward` of ``z``."""
        z = np.asarray(z, float)
        total, slopes = self._log_scales(z)
        scaled = np.exp(total) * np.asarray(grad, float)
        out = scaled.copy()
        for slope, k in zip(slopes, self.axes, strict=True):
            out[k] += float(slope @ (z * scaled))
        return out


def _drop(space: ValueSpace, plan: Reparameterization, base: np.ndarray, r: int, at: float):
    z = base.copy()
    z[r] += at
    with np.errstate(all="ignore"):
        centre, _ = plan.logp_dlogp(space, base, safe=True)
        logp, _ = plan.logp_dlogp(space, z, safe=True)
    return centre - logp if np.isfinite(logp) and np.isfinite(centre) else np.inf


def transverse_error(space: ValueSpace, plan: Reparameterization, axes: tuple[int, ...]) -> float:
    """Mean ``|drop − 1.125|`` (at most 100) at ±1.5 along the other axes, out on ``axes``.

    The drops are taken from ``z_k = a`` (``a`` in ``_ALONG``, the other coordinates at 0)
    along each axis not in ``axes``: the Gaussian score's test across the ridge, away from
    the mode.

    Examples
    --------
    >>> transverse_error(space, bent, (0,))  # doctest: +SKIP
    0.04
    """
    errors = []
    others = [r for r in range(plan.ndim) if r not in axes]
    for k in axes:
        for a in _ALONG:
            base = np.zeros(plan.ndim)
            base[k] = a
            for r in others:
                for sign in (-1.5, 1.5):
                    drop = _drop(space, plan, base, r, sign)
                    errors.append(min(abs(drop - _GAUSSIAN_DROP), 100.0))
    return float(np.mean(errors)) if errors else 0.0


def _precisions(space: ValueSpace, plan: Reparameterization, k: int, t: float, held: list[int]):
    """Diagonal of the Hessian of ``−log p`` over the unbent axes on the path at ``z_k = t``."""
    from kohpymc.bends import _conditional_mode

    mode = _conditional_mode(space, plan, k, t, held, guess=np.zeros(plan.ndim))
    if mode is None:
        return None
    mode[k] = t
    rest = np.array([r for r in range(plan.ndim) if r != k and r not in held])

    def logp_grad(y):
        z = mode.copy()
        z[rest] = y
        with np.errstate(all="ignore"):
            logp, grad = plan.logp_dlogp(space, z, safe=True)
        return logp, grad[rest]

    hess = _hessian(logp_grad, mode[rest], np.full(rest.size, 1e-3))
    diag = np.full(plan.ndim, np.nan)
    diag[rest] = np.diag(hess)
    return diag


def _fitted(space: ValueSpace, plan: Reparameterization, axes, nodes) -> Widths | None:
    """:class:`Widths` from the conditional precisions at ``nodes`` (None where not positive)."""
    logs = np.zeros((len(axes), nodes.size, plan.ndim))
    unbent = [r for r in range(plan.ndim) if r not in axes]
    for j, k in enumerate(axes):
        held = [a for a in axes if a != k]
        diags = [_precisions(space, plan, k, float(t), held) for t in nodes]
        if any(d is None for d in diags):
            return None
        diag = np.array(diags)[:, unbent]
        if not np.all(np.isfinite(diag) & (diag > 0)):
            return None
        centre = diag[int(np.flatnonzero(nodes == 0.0)[0])]
        logs[j][:, unbent] = 0.5 * np.log(centre / diag)
    return Widths(tuple(axes), np.asarray(nodes, float).copy(), logs)


def widen_plan(space: ValueSpace, plan: Any) -> Any:
    """``plan`` (a :class:`~kohpymc.bends.BentCoordinatesPlan`) with :class:`Widths`, if better.

    The widths are fitted at the bend's nodes along its bent axes and kept when they lower
    :func:`transverse_error` by :data:`WIDTH_GAIN`; otherwise ``plan`` is returned.  The
    plan's Gaussian score is recomputed (along a bent axis it now includes the
    log-Jacobian, the change of the ridge's width).

    Examples
    --------
    >>> widened = widen_plan(space, bent)  # doctest: +SKIP
    >>> widened.widths is not None  # doctest: +SKIP
    True
    """
    from kohpymc.reparameterization import _gaussian_score

    axes = tuple(int(k) for k in plan.bend.axes)
    if plan.widths is not None or not axes or len(axes) == plan.ndim:
        return plan
    widths = _fitted(space, plan, axes, plan.bend.nodes)
    if widths is None or not np.abs(widths.logs).max() > 0.05:
        return plan
    candidate = replace(plan, widths=widths)
    before = transverse_error(space, plan, axes)
    after = transverse_error(space, candidate, axes)
    if not after < (1.0 - WIDTH_GAIN) * before:
        return plan
    return replace(candidate, gaussian_score=_gaussian_score(space, candidate))
