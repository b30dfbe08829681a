r"""A ridge that bends away from its tangent at the mode, followed by a quadratic map.

Two parameters related nonlinearly (a barrier ``E_A − c/√ε_∞`` informed by the data, with
``E_A`` and ``ε_∞`` sampled in their own units) leave a thin ridge that is a parabola in
the coordinates whitened at the mode: along the ridge's tangent ``z_k`` its centre moves
``c_k z_k²`` across it, so the log density along that axis is ``−z²/2 − ½|c_k|² z⁴``, a
wall that grows with the fourth power (dielectric M0: drop 65 at 3 Laplace sd, 4.5 for a
Gaussian; its divergent transitions sit there).  :class:`Bend` measures the other
whitened coordinates from the parabola,

.. math:: z' = z + \sum_{k \in K} c_k z_k^2,\qquad (c_k)_j = 0 \text{ for } j \in K,

which is unit-triangular (``log|∂z'/∂z| = 0``) and the identity to first order at the
mode, so the whitening fitted there stays valid.  :func:`bend_plan` fits ``c_k`` from the
conditional modes of the other coordinates at ``z_k = ±reach`` and keeps the bent plan
when it scores closer to a Gaussian (:func:`kohpymc.reparameterization._gaussian_score`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import optimize
from scipy.linalg import solve_triangular

from kohpymc.reparameterization import NUMPY, ArrayMath, Reparameterization, _gaussian_score
from kohpymc.value_space import ValueSpace

__all__ = ["Bend", "BentPlan", "bend_plan"]

#: a bend is fitted when the ridge's centre moves this many transverse sds at ±reach
_MIN_SHIFT = 0.5


@dataclass(frozen=True)
class Bend:
    r"""``u' = u + B (G (u − μ))²``: the quadratic map of the module docstring in ``u = μ + L z``.

    Attributes
    ----------
    centre : ndarray
        ``μ``, the plan's mean.
    rows : ndarray
        ``G``, ``(|K|, n)``: the rows of ``L⁻¹`` of the bent axes (``z_K = G (u − μ)``).
    shifts : ndarray
        ``B = L C``, ``(n, |K|)``; ``G B = 0`` (the bent axes are not moved), so the
        map's Jacobian determinant is 1 and its inverse explicit.

    Examples
    --------
    >>> bend = Bend(np.zeros(2), np.array([[1.0, 0.0]]), np.array([[0.0], [0.5]]))
    >>> bend.forward(np.array([2.0, 0.0]))
    array([2., 2.])
    >>> bend.inverse(bend.forward(np.array([2.0, 0.3])))
    array([2. , 0.3])
    """

    centre: np.ndarray
    rows: np.ndarray
    shifts: np.ndarray

    def forward(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        """``u'`` from ``u`` (over ``xp``)."""
        s = xp.dot(self.rows, u - self.centre)
        return u + xp.dot(self.shifts, s * s)

    def inverse(self, w: np.ndarray) -> np.ndarray:
        """``u`` from ``u'`` (``G u' = G u``)."""
        s = self.rows @ (np.asarray(w, float) - self.centre)
        return w - self.shifts @ (s * s)

    def pull_back(self, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``u`` from the gradient at :meth:`forward` of ``u``."""
        s = self.rows @ (u - self.centre)
        return grad + self.rows.T @ (2.0 * s * (self.shifts.T @ grad))


@dataclass(frozen=True)
class BentPlan(Reparameterization):
    """A whitened plan with a :class:`Bend` applied to ``u = μ + L z`` first."""

    bend: Bend | None = None

    def _unshared(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        return super()._unshared(u if self.bend is None else self.bend.forward(u, xp), xp)

    def _pull_back(self, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        if self.bend is None:
            return super()._pull_back(u, grad)
        grad = super()._pull_back(self.bend.forward(u), grad)
        return self.bend.pull_back(u, grad)

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector."""
        w = self.coordinates.from_value(np.asarray(v, float))
        u = w if self.bend is None else self.bend.inverse(w)
        return solve_triangular(self.chol, u - self.mean, lower=True)

    def explained(self, white: Reparameterization) -> BentPlan:
        """The plan with ``white``'s reason (the unbent plan's) extended, and its warnings."""
        axes = 0 if self.bend is None else self.bend.rows.shape[0]
        reason = white.reason.removesuffix(")") + (
            f"; {axes} whitened axis/axes bent along the parabola the ridge follows there, "
            f"Gaussian score {white.gaussian_score:.3g} -> {self.gaussian_score:.3g})"
        )
        return replace(self, reason=reason, warnings=white.warnings)


def _conditional_mode(space: ValueSpace, plan: Reparameterization, k: int, at: float):
    """The other whitened coordinates' conditional mode at ``z_k = at`` (None if not found)."""
    n = plan.ndim
    rest = np.array([i for i in range(n) if i != k], dtype=int)

    def objective(y):
        z = np.zeros(n)
        z[k], z[rest] = at, y
        with np.errstate(all="ignore"):
            logp, grad = plan.logp_dlogp(space, z, safe=True)
        if not np.isfinite(logp) or not np.all(np.isfinite(grad)):
            return np.inf, np.zeros(rest.size)
        return -logp, -grad[rest]

    if not np.isfinite(objective(np.zeros(rest.size))[0]):
        return None
    result = optimize.minimize(
        objective, np.zeros(rest.size), jac=True, method="L-BFGS-B", options={"maxiter": 300}
    )
    if not np.isfinite(result.fun):
        return None
    out = np.zeros(n)
    out[rest] = result.x
    return out


def _coefficients(space: ValueSpace, plan: Reparameterization, reach: float) -> np.ndarray:
    """``C`` (column ``k``: the parabola's coefficients along axis ``k``; NaN if not found)."""
    n = plan.ndim
    coefs = np.full((n, n), np.nan)
    for k in range(n):
        low = _conditional_mode(space, plan, k, -reach)
        high = _conditional_mode(space, plan, k, reach)
        if low is not None and high is not None:
            coefs[:, k] = (low + high) / (2.0 * reach**2)
    return coefs


def bend_plan(
    space: ValueSpace, plan: Reparameterization, *, reach: float = 1.5
) -> BentPlan | None:
    """``plan`` with a :class:`Bend` along its bent axes (None: none bent, or it scores worse).

    An axis ``k`` is bent when the conditional mode of the others moves more than
    ``_MIN_SHIFT`` transverse sds symmetrically at ``z_k = ±reach``; the axes are taken
    most bent first, and each one's coefficients on the bent axes are set to zero.

    Parameters
    ----------
    space : ValueSpace
    plan : Reparameterization
        A whitened plan (``v = coordinates(μ + L z)``, not a ridge or box plan).
    reach : float
        Where the parabola is fitted, in Laplace sds (also where the Gaussian score looks).

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> from kohpymc.reparameterization import plan as make_plan
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:  # a banana: y − x² informed, x from its prior
    ...     x = pm.Normal("x", 0.0, 1.0)
    ...     y = pm.Normal("y", 0.0, 10.0)
    ...     _ = pm.Normal("obs", y - 2.0 * x**2, 0.1, observed=[0.0])
    >>> space = value_space(model)
    >>> bent = bend_plan(space, make_plan(space, seed=1))
    >>> bent.kind
    'bent-affine'
    """
    if type(plan) is not Reparameterization or plan.ndim < 2:
        return None
    coefs = _coefficients(space, plan, reach)
    size = np.linalg.norm(np.nan_to_num(coefs, nan=0.0), axis=0) * reach**2
    bent = [int(k) for k in np.argsort(-size) if size[k] > _MIN_SHIFT]
    if not bent:
        return None
    chosen = coefs[:, bent].copy()
    chosen[bent, :] = 0.0
    inverse = solve_triangular(plan.chol, np.eye(plan.ndim), lower=True)
    bend = Bend(plan.mean.copy(), inverse[bent], plan.chol @ chosen)
    base = {k: v for k, v in plan.__dict__.items() if k != "kind"}
    candidate = BentPlan(kind=f"bent-{plan.kind}", bend=bend, **base)
    score = _gaussian_score(space, candidate)
    if not score < plan.gaussian_score:
        return None
    return replace(candidate, gaussian_score=score)
