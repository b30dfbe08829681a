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
when it scores at least 10 % closer to a Gaussian
(:func:`kohpymc.reparameterization._gaussian_score`).
An axis whose own marginal has light tails (drop above 9 at ±3 sd after the bend; dielectric
M1's ln γ axis: 24–32, and 115–162 at ±4) is then squeezed (:class:`Squeeze`), which makes a
quartic tail Gaussian.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from typing import Any, ClassVar

import numpy as np
from scipy import optimize
from scipy.interpolate import CubicSpline
from scipy.linalg import solve_triangular

from kohpymc.reparameterization import (
    NUMPY,
    ArrayMath,
    Reparameterization,
    _axis_errors,
    _drop,
    _gaussian_score,
)
from kohpymc.value_space import ValueSpace

__all__ = [
    "Bend",
    "BentCoordinatesPlan",
    "BentPlan",
    "CurveBend",
    "PairSurface",
    "bend_coordinates",
    "bend_plan",
    "follow_plan",
]

#: a bend is fitted when the ridge's centre moves this many transverse sds at ±reach
_MIN_SHIFT = 0.5

#: a bend is kept (and its light-tailed axes squeezed) only when it lowers the Gaussian
#: score by at least this share.  A bend that changes nothing leaves the score to the
#: squeeze, which is fitted to the very drops the score measures (with the other axes at
#: 0) and so always looks Gaussian, also on an axis whose marginal is wide because the
#: others widen along it (a funnel): Nusselt-correlation M3, bend 2.783 -> 2.781, squeezed
#: to 0.248 with β = 25 (4 × 1000 draws reaching 650 sds in z: r̂ 1.21, bulk ESS 15,
#: 529 s), where the ridge curve (0.396) samples it (2 × 1000: r̂ 1.02, ESS 154, 240 s)
_BEND_GAIN = 0.1


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
class Squeeze:
    r"""Light-tailed whitened axes squeezed: ``s_k → s_k (1 + β_k s_k²)^{−1/4}``.

    Along an axis whose log density falls like ``−z²/2 − c z⁴`` (a marginal with light
    tails, which no bend removes) NUTS's step, adapted to the bulk, is unstable in the tails.
    Sampling ``y`` with ``s = y (1 + β y²)^{−1/4}`` turns a quartic tail in ``s`` into a
    Gaussian one in ``y``.  In ``u``: ``u' = u + Σ_k a_k (φ_k(s_k) − s_k)`` with
    ``s_k = g_k·(u − μ)``, ``g_k`` the rows of ``L⁻¹`` and ``a_k = L e_k``
    (``g_j·a_k = δ_jk``), so ``log|∂u'/∂u| = Σ_k log φ_k'(s_k)``.

    Examples
    --------
    >>> squeeze = Squeeze(np.zeros(1), np.eye(1), np.eye(1), np.array([0.5]))
    >>> bool(np.allclose(squeeze.inverse(squeeze.forward(np.array([2.0]))), 2.0))
    True
    """

    centre: np.ndarray
    rows: np.ndarray
    columns: np.ndarray
    beta: np.ndarray

    def _s(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        return xp.dot(self.rows, u - self.centre)

    def forward(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        """``u'`` from ``u`` (over ``xp``)."""
        s = self._s(u, xp)
        t = s * xp.exp(-0.25 * xp.log(1.0 + self.beta * s * s))
        return u + xp.dot(self.columns, t - s)

    def log_jacobian(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        """``Σ_k log φ_k'(s_k)`` (over ``xp``)."""
        q = self.beta * self._s(u, xp) ** 2
        return xp.sum(xp.log(1.0 + 0.5 * q) - 1.25 * xp.log(1.0 + q))

    def derivatives(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``φ_k'(s_k)`` and ``d log φ_k'(s_k) / ds_k``."""
        s = self._s(u)
        q = self.beta * s * s
        slope = (1.0 + 0.5 * q) * (1.0 + q) ** -1.25
        return slope, self.beta * s / (1.0 + 0.5 * q) - 2.5 * self.beta * s / (1.0 + q)

    def inverse(self, w: np.ndarray) -> np.ndarray:
        """``u`` from ``u'``: ``s⁴ = t⁴ (1 + β s²)`` solved for ``s²``."""
        t = self._s(np.asarray(w, float))
        t4 = t**4
        s = np.sign(t) * np.sqrt(0.5 * (self.beta * t4 + np.sqrt((self.beta * t4) ** 2 + 4 * t4)))
        return w + self.columns @ (s - t)

    def pull_back(self, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``u`` from the gradient at :meth:`forward` of ``u``."""
        slope, _ = self.derivatives(u)
        return grad + self.rows.T @ ((slope - 1.0) * (self.columns.T @ grad))


@dataclass(frozen=True)
class BentPlan(Reparameterization):
    """A whitened plan with a :class:`Squeeze` and a :class:`Bend` applied to ``u = μ + L z``."""

    curved: ClassVar[bool] = True
    bend: Bend | None = None
    squeeze: Squeeze | None = None

    def _squeezed(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        return u if self.squeeze is None else self.squeeze.forward(u, xp)

    def _map_arrays(self) -> list[np.ndarray]:
        """The bend's and the squeeze's arrays, in :meth:`map_constants` order."""
        arrays = []
        if self.bend is not None:
            arrays += [self.bend.centre, self.bend.rows, self.bend.shifts]
        if self.squeeze is not None:
            s = self.squeeze
            arrays += [s.centre, s.rows, s.columns, s.beta]
        return [np.asarray(a, dtype=float) for a in arrays]

    def map_constants(self) -> np.ndarray:
        """The bend's centre, rows and shifts, then the squeeze's centre, rows, columns, β."""
        arrays = self._map_arrays()
        return np.concatenate([a.ravel() for a in arrays]) if arrays else np.zeros(0)

    def with_map_constants(self, values: Any) -> BentPlan:
        """The plan with its bend and squeeze read from ``values`` (e.g. a tensor slice).

        Examples
        --------
        >>> bend = Bend(np.zeros(2), np.array([[1.0, 0.0]]), np.array([[0.0], [0.5]]))
        >>> plan = BentPlan("bent-affine", np.zeros(2), np.eye(2), None, "", bend=bend)
        >>> copy = plan.with_map_constants(2.0 * plan.map_constants())
        >>> copy.bend.shifts.tolist()
        [[0.0], [1.0]]
        """
        parts, start = [], 0
        for array in self._map_arrays():
            parts.append(values[start : start + array.size].reshape(array.shape))
            start += array.size
        bend, squeeze = self.bend, self.squeeze
        if bend is not None:
            bend = Bend(*parts[:3])
            parts = parts[3:]
        if squeeze is not None:
            squeeze = Squeeze(*parts)
        return replace(self, bend=bend, squeeze=squeeze)

    def _unshared(self, u: Any, xp: ArrayMath = NUMPY) -> Any:
        u = self._squeezed(u, xp)
        return super()._unshared(u if self.bend is None else self.bend.forward(u, xp), xp)

    def _pull_back(self, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
        squeezed = self._squeezed(u)
        bent = squeezed if self.bend is None else self.bend.forward(squeezed)
        grad = super()._pull_back(bent, grad)
        grad = grad if self.bend is None else self.bend.pull_back(squeezed, grad)
        return grad if self.squeeze is None else self.squeeze.pull_back(u, grad)

    def value_from_affine(self, u: Any, xp: ArrayMath = NUMPY) -> tuple[Any, Any]:
        """``v`` and the log-Jacobian, the squeeze's included (over ``xp``)."""
        v, logjac = super().value_from_affine(u, xp)
        return v, logjac if self.squeeze is None else logjac + self.squeeze.log_jacobian(u, xp)

    def logp_dlogp(
        self, space: ValueSpace, z: np.ndarray, *, safe: bool = False
    ) -> tuple[float, np.ndarray]:
        """Log density of ``z`` (exact up to a constant) and its gradient."""
        logp, grad = super().logp_dlogp(space, z, safe=safe)
        if self.squeeze is None or not np.isfinite(logp):
            return logp, grad
        u = self.mean + self.chol @ np.asarray(z, float)
        _, dlog = self.squeeze.derivatives(u)
        grad = grad + self.chol.T @ (self.squeeze.rows.T @ dlog)
        return logp + float(self.squeeze.log_jacobian(u)), grad

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector."""
        w = self.coordinates.from_value(np.asarray(v, float))
        u = w if self.bend is None else self.bend.inverse(w)
        u = u if self.squeeze is None else self.squeeze.inverse(u)
        return solve_triangular(self.chol, u - self.mean, lower=True)

    def explained(self, white: Reparameterization) -> BentPlan:
        """The plan with ``white``'s reason (the unbent plan's) extended, and its warnings."""
        axes = 0 if self.bend is None else self.bend.rows.shape[0]
        reason = white.reason.removesuffix(")") + (
            f"; {axes} whitened axis/axes bent along the parabola the ridge follows there, "
            f"Gaussian score {white.gaussian_score:.3g} -> {self.gaussian_score:.3g})"
        )
        return replace(self, reason=reason, warnings=white.warnings)


def _conditional_mode(
    space: ValueSpace,
    plan: Reparameterization,
    k: int,
    at: float,
    held: Sequence[int] = (),
    fixed: dict[int, float] | None = None,
    *,
    guess: np.ndarray | None = None,
    options: dict[str, Any] | None = None,
):
    """The other whitened coordinates' conditional mode at ``z_k = at`` (None if not found).

    The coordinates ``held`` stay at 0, or at ``fixed[i]`` where given.  L-BFGS starts
    from ``guess`` (a full ``z``; default 0) with ``options`` (default ``maxiter`` 300).
    """
    n = plan.ndim
    rest = np.array([i for i in range(n) if i != k and i not in held], dtype=int)
    start = np.zeros(n)
    for i, value in (fixed or {}).items():
        start[i] = value
    first = np.zeros(rest.size) if guess is None else np.asarray(guess, float)[rest]

    def objective(y):
        z = start.copy()
        z[k], z[rest] = at, y
        with np.errstate(all="ignore"):
            logp, grad = plan.logp_dlogp(space, z, safe=True)
        if not np.isfinite(logp) or not np.all(np.isfinite(grad)):
            return np.inf, np.zeros(rest.size)
        return -logp, -grad[rest]

    if not np.isfinite(objective(first)[0]):
        return None
    result = optimize.minimize(
        objective, first, jac=True, method="L-BFGS-B", options=options or {"maxiter": 300}
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
    """``plan`` with a :class:`Bend` along its bent axes (None: none bent, or no better).

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
    >>> bent = make_plan(value_space(model), seed=1)  # plan() calls bend_plan
    >>> bent.kind, bent.bend.rows.shape  # x's whitened axis bent
    ('bent-affine', (1, 2))
    """
    if type(plan) is not Reparameterization or plan.ndim < 2:
        return None
    axes = _bent_axes(space, plan, reach)
    if axes is None:
        return None
    bent, chosen = axes
    inverse = solve_triangular(plan.chol, np.eye(plan.ndim), lower=True)
    bend = Bend(plan.mean.copy(), inverse[bent], plan.chol @ chosen)
    base = {k: v for k, v in plan.__dict__.items() if k != "kind"}
    candidate = BentPlan(kind=f"bent-{plan.kind}", bend=bend, **base)
    score = _gaussian_score(space, candidate)
    if not score < (1.0 - _BEND_GAIN) * plan.gaussian_score:
        return None
    return _squeezed_plan(space, replace(candidate, gaussian_score=score), inverse)


def _bent_axes(
    space: ValueSpace, plan: Reparameterization, reach: float, *, targets_first: bool = False
) -> tuple[list[int], np.ndarray] | None:
    """The bent axes of ``plan``'s ``z``, most bent first, and their coefficients ``C``.

    Axis ``k`` is bent when the conditional mode of the others moves more than
    ``_MIN_SHIFT`` sds symmetrically at ``z_k = ±reach``; the coefficients on the bent axes
    are set to zero (none is moved by another's bend).  With ``targets_first``, an axis that
    a more bent one moves by more than ``_MIN_SHIFT`` stays a target and is not bent itself
    (dielectric M2's ridge curve: E_A's axis, bent 0.6, would have cancelled the 4.9 sds
    that ε_∞'s parabola moves it).  None when no axis is bent.
    """
    coefs = _coefficients(space, plan, reach)
    shifts = np.nan_to_num(coefs, nan=0.0) * reach**2
    size = np.linalg.norm(shifts, axis=0)
    bent: list[int] = []
    for k in (int(k) for k in np.argsort(-size) if size[k] > _MIN_SHIFT):
        if not (targets_first and bent and np.abs(shifts[k, bent]).max() > _MIN_SHIFT):
            bent.append(k)
    if not bent:
        return None
    chosen = coefs[:, bent].copy()
    chosen[bent, :] = 0.0
    return bent, chosen


#: where :func:`bend_coordinates` finds the conditional modes along a bent axis (beyond
#: the outer nodes the path goes on straight)
_CURVE_NODES = np.array([-4.5, -3.0, -1.5, 0.0, 1.5, 3.0, 4.5])


#: nodes of a :class:`PairSurface` along both of its axes (in sds; 0 is where it vanishes)
_SURFACE_NODES = np.array([-3.0, -1.5, 0.0, 1.5, 3.0])


@dataclass(frozen=True)
class PairSurface:
    r"""``S(z_k, z_j) = Σ_ab b_a(z_k) b_b(z_j) V_ab``: the others' shift that two axes make jointly.

    ``b`` are the cardinal natural cubic splines on ``nodes`` (continued along their end
    tangents), so ``S`` interpolates ``V`` at the grid and reproduces a bilinear term
    exactly; ``V`` is zero where ``z_k`` or ``z_j`` is 0, so ``S`` leaves either axis alone
    unchanged.  Dielectric M2: along ε_∞'s bent axis with ln γ's axis at −2 sd jointly, E_A's
    conditional mode moves 3.4 sds more than the two paths added (one quadrant only, so no
    bilinear term fits it); the joint drop there was 10.1, 4.0 for a Gaussian.

    Examples
    --------
    >>> nodes = np.array([-1.0, 0.0, 1.0])
    >>> values = np.zeros((3, 3, 3))
    >>> values[[0, 2], [0, 2], 2], values[[0, 2], [2, 0], 2] = 1.0, -1.0  # z_k·z_j on axis 2
    >>> PairSurface(0, 1, nodes, values).value(np.array([2.0, 0.5, 0.0]))
    array([0., 0., 1.])
    """

    k: int
    j: int
    nodes: np.ndarray
    values: np.ndarray  # (len(nodes), len(nodes), n)

    @cached_property
    def _basis(self) -> CubicSpline:
        return CubicSpline(self.nodes, np.eye(self.nodes.size), axis=0, bc_type="natural")

    def _b(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The basis values at ``t`` and their derivatives."""
        end = min(max(t, self.nodes[0]), self.nodes[-1])
        slope = self._basis(end, 1)
        return self._basis(end) + slope * (t - end), slope

    def value(self, z: np.ndarray) -> np.ndarray:
        """``S`` at ``z``."""
        bk, _ = self._b(float(z[self.k]))
        bj, _ = self._b(float(z[self.j]))
        return np.einsum("a,b,abn->n", bk, bj, self.values)

    def slopes(self, z: np.ndarray, grad: np.ndarray) -> tuple[float, float]:
        """``∂(S·grad)/∂z_k`` and ``∂(S·grad)/∂z_j``."""
        bk, dk = self._b(float(z[self.k]))
        bj, dj = self._b(float(z[self.j]))
        along = self.values @ grad
        return float(dk @ along @ bj), float(bk @ along @ dj)


@dataclass(frozen=True)
class CurveBend:
    r"""``z' = z + Σ_k φ_k(z_k)``: the others follow their conditional modes along axes ``K``.

    ``φ_k`` is a natural cubic spline through the shifts of the conditional modes of the
    other coordinates at nodes of ``z_k`` (zero at 0, zero on the bent axes), continued
    along its end tangents beyond the outer nodes.  A parabola fitted at ±1.5 sds
    (:class:`Bend`) overshoots a ridge that curves less further out (dielectric M2's
    ε_∞–E_A ridge: at ε_∞'s z = 3.3 the parabola puts E_A 12 sds past the ridge, where
    NUTS diverged); the spline follows it.  Unit-triangular, inverse explicit.

    Examples
    --------
    >>> bend = CurveBend((0,), np.array([-1.0, 0.0, 1.0]), np.array([[[0, 1.0], [0, 0], [0, 1.0]]]))
    >>> bend.forward(np.array([1.0, 0.0]))
    array([1., 1.])
    >>> bend.inverse(bend.forward(np.array([2.0, 0.3])))
    array([2. , 0.3])
    """

    axes: tuple[int, ...]
    nodes: np.ndarray
    shifts: np.ndarray  # (|K|, len(nodes), n)
    #: ``{(j, l): c}``: a term ``c z_{K_j} z_{K_l}`` for bent axes whose paths interact
    cross: tuple[tuple[int, int, np.ndarray], ...] = ()
    #: the splines' end conditions (SciPy's ``bc_type``)
    ends: str = "natural"
    #: joint shifts of a bent axis and a *partner* (an unbent axis moved, if at all, only by
    #: the bent axes' paths and cross terms); zero on the bent axes and the partners
    surfaces: tuple[PairSurface, ...] = ()

    @cached_property
    def _splines(self) -> list[CubicSpline]:
        return [CubicSpline(self.nodes, path, axis=0, bc_type=self.ends) for path in self.shifts]

    def _phi(self, j: int, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``φ_j(t)`` and ``φ_j'(t)``."""
        spline = self._splines[j]
        lo, hi = self.nodes[0], self.nodes[-1]
        end = min(max(t, lo), hi)
        slope = spline(end, 1)
        return spline(end) + slope * (t - end), slope

    def _paths(self, z: np.ndarray) -> np.ndarray:
        """The shift that depends on the bent axes alone (their paths and cross terms)."""
        out = np.zeros(z.size)
        for j, k in enumerate(self.axes):
            out += self._phi(j, float(z[k]))[0]
        for a, b, c in self.cross:
            out += c * (z[self.axes[a]] * z[self.axes[b]])
        return out

    def _joint(self, z: np.ndarray) -> np.ndarray:
        return sum((s.value(z) for s in self.surfaces), np.zeros(z.size))

    def forward(self, z: np.ndarray) -> np.ndarray:
        """``z'`` from ``z``."""
        z = np.asarray(z, float)
        return z + self._paths(z) + self._joint(z)

    def inverse(self, w: np.ndarray) -> np.ndarray:
        """``z`` from ``z'``: the bent axes are not moved, the partners only by them."""
        w = np.asarray(w, float)
        base = w - self._paths(w)
        return base - self._joint(base)

    def pull_back(self, z: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Gradient with respect to ``z`` from the gradient at :meth:`forward` of ``z``."""
        out = np.array(grad, dtype=float)
        for j, k in enumerate(self.axes):
            out[k] += float(self._phi(j, float(z[k]))[1] @ grad)
        for a, b, c in self.cross:
            along = float(c @ grad)
            out[self.axes[a]] += along * z[self.axes[b]]
            out[self.axes[b]] += along * z[self.axes[a]]
        for surface in self.surfaces:
            dk, dj = surface.slopes(z, grad)
            out[surface.k] += dk
            out[surface.j] += dj
        return out


@dataclass(frozen=True)
class BentCoordinatesPlan(Reparameterization):
    """A plan with its own map (e.g. a ridge curve) bent in its sampling coordinates.

    ``z' = z + Σ_k φ_k(z_k)`` (a :class:`CurveBend`) before ``inner``'s map:
    unit-triangular, so the density of ``z`` is ``inner``'s at ``z'``.
    """

    #: ``inner``'s own map has no symbolic form (nutpie calls this plan from Python)
    symbolic: ClassVar[bool] = False
    curved: ClassVar[bool] = True
    inner: Any = None
    bend: CurveBend = field(default_factory=lambda: CurveBend((), np.zeros(2), np.zeros((0, 2, 0))))

    def to_value(self, z: np.ndarray) -> np.ndarray:
        """PyMC value-space vector of sampling coordinates ``z``."""
        return self.inner.to_value(self.bend.forward(np.asarray(z, float)))

    def explained(self, white: Reparameterization) -> BentCoordinatesPlan:
        """The plan with ``white``'s reason (the unbent plan's) extended, and its warnings."""
        reason = white.reason.removesuffix(")") + (
            f"; {len(self.bend.axes)} whitened axis/axes followed along the path of the "
            f"others' conditional modes, Gaussian score {white.gaussian_score:.3g} -> "
            f"{self.gaussian_score:.3g})"
        )
        return replace(self, reason=reason, warnings=white.warnings)

    def from_value(self, v: np.ndarray) -> np.ndarray:
        """Sampling coordinates of a value-space vector."""
        return self.bend.inverse(self.inner.from_value(v))

    def laplace_value_sd(self) -> np.ndarray:
        """``inner``'s."""
        return self.inner.laplace_value_sd()

    def logp_dlogp(
        self, space: ValueSpace, z: np.ndarray, *, safe: bool = False
    ) -> tuple[float, np.ndarray]:
        """Log density of ``z`` (exact up to a constant) and its gradient."""
        z = np.asarray(z, float)
        logp, grad = self.inner.logp_dlogp(space, self.bend.forward(z), safe=safe)
        return logp, self.bend.pull_back(z, grad)


def _mode_path(
    space: ValueSpace,
    plan: Reparameterization,
    k: int,
    bent: list[int],
    nodes: np.ndarray = _CURVE_NODES,
    guesses: np.ndarray | None = None,
) -> np.ndarray | None:
    """Shifts of the others' conditional modes at ``nodes`` of ``z_k`` (which hold 0).

    Relative to the mode at ``z_k = 0``, with the other bent axes held at 0 (where the
    map leaves them); each search starts from the centre plus ``guesses`` (shifts, one row
    per node; default none).  None where a mode is not found.
    """
    centre = _conditional_mode(space, plan, k, 0.0, bent)
    if centre is None:
        return None
    shifts = np.zeros((nodes.size, plan.ndim))
    for i, t in enumerate(nodes):
        guess = None if guesses is None else centre + guesses[i]
        mode = (
            centre if t == 0.0 else _conditional_mode(space, plan, k, float(t), bent, guess=guess)
        )
        if mode is None:
            return None
        shifts[i] = mode - centre
    shifts[:, bent] = 0.0
    return shifts


def _paths(
    space: ValueSpace,
    plan: Reparameterization,
    bent: list[int],
    nodes: np.ndarray,
    guesses: Sequence[np.ndarray] | None = None,
) -> list[np.ndarray] | None:
    """:func:`_mode_path` of every bent axis (None if one is not found)."""
    paths = []
    for j, k in enumerate(bent):
        path = _mode_path(space, plan, k, bent, nodes, None if guesses is None else guesses[j])
        if path is None:
            return None
        paths.append(path)
    return paths


#: rounds of midpoints added to :data:`_CURVE_NODES` where a path bends between its nodes
_REFINE_ROUNDS = 3


def _refined_paths(
    space: ValueSpace, plan: Reparameterization, bent: list[int]
) -> tuple[np.ndarray, np.ndarray] | None:
    """Nodes and the bent axes' paths, with midpoints added where the splines miss.

    Starting from :data:`_CURVE_NODES`, the conditional modes are found at the midpoints
    of the intervals, each search starting on the spline through the nodes (so that it
    stays on the ridge the path follows); where a mode lies more than ``_MIN_SHIFT`` sds
    from the spline, the midpoint becomes a node (for every bent axis), for at most
    :data:`_REFINE_ROUNDS` rounds.  The Gaussian score probes ±1.5 sds, which are nodes,
    so it cannot see a spline that swings between them: Nusselt-correlation M3's ridge
    curve, whose others' conditional modes turn within 0.5 sd of its narrow end, was
    bent 10–12 sds off the ridge at ``z = 0.8–1.0`` (log density 200–300 below the path's;
    2 × 1000 draws: 30 divergences there, bulk ESS 40).  None where a mode is not found.
    """
    nodes = _CURVE_NODES.copy()
    paths = _paths(space, plan, bent, nodes)
    for _ in range(_REFINE_ROUNDS):
        if paths is None:
            return None
        mids = 0.5 * (nodes[1:] + nodes[:-1])
        splines = [CubicSpline(nodes, p, axis=0, bc_type="natural") for p in paths]
        found = _paths(space, plan, bent, mids, [s(mids) for s in splines])
        if found is None:
            return None
        miss = [np.abs(f - s(mids)).max(axis=1) for f, s in zip(found, splines, strict=True)]
        added = np.max(miss, axis=0) > _MIN_SHIFT
        if not added.any():
            break
        order = np.argsort(np.concatenate([nodes, mids[added]]), kind="stable")
        nodes = np.concatenate([nodes, mids[added]])[order]
        paths = [np.concatenate([p, f[added]])[order] for p, f in zip(paths, found, strict=True)]
    if paths is None:
        return None
    return nodes, np.array(paths)


def _interactions(space: ValueSpace, plan: Reparameterization, bent: list[int], at: float = 2.0):
    """Bilinear terms between bent axes from the others' conditional modes at ``(±at, ±at)``.

    ``c = [m(+,+) + m(−,−) − m(+,−) − m(−,+)] / (4 at²)`` (zero on the bent axes), the part
    of the ridge's path that the axes' own paths, added, miss (dielectric M2: ε_∞'s and
    ln N_T's paths added leave a drop of 227 at 3.2 sds on both, 10.1 for a Gaussian).
    None where a mode is not found.
    """
    cross = []
    pairs = [(a, b) for a in range(len(bent)) for b in range(a + 1, len(bent))]
    for a, b in pairs:
        corners = []
        for sa, sb in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
            others = [k for k in bent if k != bent[a]]
            mode = _conditional_mode(space, plan, bent[a], sa * at, others, {bent[b]: sb * at})
            if mode is None:
                return None
            corners.append(mode)
        c = (corners[0] + corners[1] - corners[2] - corners[3]) / (4 * at**2)
        c[bent] = 0.0
        cross.append((a, b, c))
    return tuple(cross)


#: a bent axis and another interact when their joint drop at (±2, ±2) sds misses the sum
#: of their own drops by more than this (0 for a Gaussian in whitened coordinates)
_JOINT_EXCESS = 1.0

#: at most this many pair surfaces per plan (each costs 25 conditional modes)
_MAX_SURFACES = 3


def _drop_at(space: ValueSpace, plan: Reparameterization, point: dict[int, float]) -> float:
    z = np.zeros(plan.ndim)
    for i, value in point.items():
        z[i] = value
    return _drop(space, plan, z)


def _joint_excess(space: ValueSpace, plan: Reparameterization, k: int, j: int) -> float:
    """Largest ``|drop(±2, ±2) − drop(±2, 0) − drop(0, ±2)|`` of axes ``k`` and ``j``."""
    excess = 0.0
    for a in (-2.0, 2.0):
        for b in (-2.0, 2.0):
            joint = _drop_at(space, plan, {k: a, j: b})
            alone = _drop_at(space, plan, {k: a}) + _drop_at(space, plan, {j: b})
            excess = max(excess, abs(joint - alone) if np.isfinite(joint) else np.inf)
    return excess


def _surface(
    space: ValueSpace, plan: Reparameterization, k: int, j: int, held: list[int]
) -> np.ndarray | None:
    """``R(a, b) = m(a, b) − m(a, 0) − m(0, b) + m(0, 0)`` at :data:`_SURFACE_NODES`.

    ``m`` is the others' conditional mode with ``z_k = a``, ``z_j = b`` and ``held`` at 0;
    ``R`` is what the two axes' own paths miss jointly (zero on both axes).  None where a
    mode is not found.
    """
    nodes = _SURFACE_NODES
    others = [i for i in held if i not in (k, j)]

    def mode(a: float, b: float, guess: np.ndarray | None = None) -> np.ndarray | None:
        return _conditional_mode(space, plan, k, a, [*others, j], {j: b}, guess=guess)

    centre = mode(0.0, 0.0)
    along_k = {float(a): mode(float(a), 0.0) for a in nodes if a != 0.0}
    along_j = {}
    for b in (float(b) for b in nodes if b != 0.0):
        along_j[b] = _conditional_mode(space, plan, j, b, [*others, k])
    if centre is None or any(m is None for m in (*along_k.values(), *along_j.values())):
        return None
    values = np.zeros((nodes.size, nodes.size, plan.ndim))
    for ia, a in enumerate(nodes):
        for ib, b in enumerate(nodes):
            if a == 0.0 or b == 0.0:
                continue
            guess = along_k[a] + along_j[b] - centre
            guess[k], guess[j] = a, b
            joint = mode(float(a), float(b), guess)
            if joint is None:
                return None
            values[ia, ib] = joint - along_k[a] - along_j[b] + centre
    values[:, :, [k, j, *others]] = 0.0
    return values


def _pair_surfaces(
    space: ValueSpace, plan: Reparameterization, bent: list[int]
) -> tuple[PairSurface, ...]:
    """Surfaces for the bent axes' strongest interactions with unbent partners.

    Pairs whose joint drop is not additive (:data:`_JOINT_EXCESS`) are taken strongest
    first; a surface is kept when it moves the others more than ``_MIN_SHIFT`` sds, and a
    partner may not be an axis that a kept surface moves (the map stays triangular:
    bent axes, then partners, then the rest).
    """
    pairs = []
    for k in bent:
        for j in (j for j in range(plan.ndim) if j not in bent):
            excess = _joint_excess(space, plan, k, j)
            if excess > _JOINT_EXCESS:
                pairs.append((excess, k, j))
    kept: list[PairSurface] = []
    for _, k, j in sorted(pairs, reverse=True):
        partners = [s.j for s in kept]
        moved = max((float(np.abs(s.values[:, :, j]).max()) for s in kept), default=0.0)
        if len(kept) == _MAX_SURFACES or moved > _MIN_SHIFT or k in partners:
            continue
        values = _surface(space, plan, k, j, [*bent, *partners])
        if values is None or np.abs(values).max() <= _MIN_SHIFT:
            continue
        drivers = [*bent, *partners, j]
        kept = [replace(s, values=_zeroed(s.values, drivers)) for s in kept]
        kept.append(PairSurface(k, j, _SURFACE_NODES.copy(), _zeroed(values, drivers)))
    return tuple(kept)


def _zeroed(values: np.ndarray, axes: list[int]) -> np.ndarray:
    out = values.copy()
    out[:, :, axes] = 0.0
    return out


def bend_coordinates(
    space: ValueSpace, plan: Reparameterization, *, reach: float = 1.5
) -> BentCoordinatesPlan | None:
    """``plan`` (any map ``z → v``) bent along its curved axes, if that scores better.

    The axes are chosen as in :func:`bend_plan` (in ``plan``'s own ``z``, an axis that a
    more bent one moves staying its target); each is followed by a :class:`CurveBend`
    through the conditional modes at :data:`_CURVE_NODES`, refined where the path bends
    between them (:func:`_refined_paths`).

    Examples
    --------
    >>> bent = bend_coordinates(space, curve)  # doctest: +SKIP
    >>> bent.kind  # doctest: +SKIP
    'bent-ridge-curve-soft-box'
    """
    axes = _bent_axes(space, plan, reach, targets_first=True)
    if axes is None:
        return None
    bent, _ = axes
    refined = _refined_paths(space, plan, bent)
    if refined is None:
        return None
    cross = _interactions(space, plan, bent)
    if cross is None:
        return None
    bend = CurveBend(tuple(bent), *refined, cross)
    base = {f.name: getattr(plan, f.name) for f in fields(Reparameterization)}
    candidate = BentCoordinatesPlan(**{**base, "kind": f"bent-{plan.kind}"}, inner=plan, bend=bend)
    score = _gaussian_score(space, candidate)
    if not score < plan.gaussian_score:
        return None
    # the surfaces vanish along every single axis, so they leave the score as it is
    surfaces = _pair_surfaces(space, candidate, bent)
    if surfaces:
        candidate = replace(candidate, bend=replace(bend, surfaces=surfaces))
    return replace(candidate, gaussian_score=score)


#: where :func:`follow_plan` finds the conditional modes along an axis (and at minus these):
#: dense near the mode, where a ridge that bends fast leaves its tangent (dielectric M3: the
#: others' conditional mode 0.5, 7.8, 49 and 177 transverse sds off at z = 0.05, 0.2, 0.5, 1)
_FOLLOW_NODES = np.array([0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.5])

#: an axis is followed when its drop at ±1.5 sd misses a Gaussian's (1.125) by more than this
_FOLLOW_ERROR = 1.0

#: L-BFGS settings of the marched conditional modes (the mode moves hundreds of sds)
_FOLLOW_OPTIONS = {"maxiter": 3000, "ftol": 1e-13, "gtol": 1e-8}


def _marched_path(
    space: ValueSpace, plan: Reparameterization, k: int, held: list[int]
) -> np.ndarray | None:
    """The others' conditional modes at ``±_FOLLOW_NODES`` of ``z_k``, marched outwards.

    Each optimisation starts from the linear extrapolation of the two previous modes: from
    0, L-BFGS stops short of a mode that lies hundreds of sds away (dielectric M3, where
    :func:`bend_plan`'s parabolas scored 45–62 against the unbent 22.5).  The axes ``held``
    stay at 0 and are not moved.  Rows follow ``_follow_nodes()``; None where a mode is not
    found.
    """
    modes = {0.0: np.zeros(plan.ndim)}
    for side in (_FOLLOW_NODES, -_FOLLOW_NODES):
        previous = [(0.0, np.zeros(plan.ndim))]
        for t in side:
            guess = previous[-1][1]
            if len(previous) > 1:
                (ta, xa), (tb, xb) = previous[-2], previous[-1]
                guess = xb + (xb - xa) * (t - tb) / (tb - ta)
            mode = _conditional_mode(
                space, plan, k, float(t), held, guess=guess, options=_FOLLOW_OPTIONS
            )
            if mode is None:
                return None
            modes[float(t)] = mode
            previous.append((float(t), mode))
    path = np.array([modes[float(t)] for t in _follow_nodes()])
    path[:, [k, *held]] = 0.0
    return path


def _follow_nodes() -> np.ndarray:
    return np.concatenate([-_FOLLOW_NODES[::-1], [0.0], _FOLLOW_NODES])


def follow_plan(space: ValueSpace, plan: Reparameterization) -> BentCoordinatesPlan | None:
    """``plan`` with its badly fitting axes followed along the others' conditional modes.

    Every axis whose log density drops at ±1.5 sd more than ``_FOLLOW_ERROR`` away from a
    Gaussian's is bent by a :class:`CurveBend` through the conditional modes at dense nodes
    (:data:`_FOLLOW_NODES`), found by marching outwards from the mode; kept when it scores
    better.  For a ridge that bends away from its tangent within a fraction of a Laplace
    sd, where neither a parabola (:func:`bend_plan`) nor the default nodes of
    :func:`bend_coordinates` follow it (dielectric M3: score 22.5 → 0.26).

    Examples
    --------
    >>> followed = follow_plan(space, laplace)  # doctest: +SKIP
    >>> followed.kind  # doctest: +SKIP
    'followed-affine'
    """
    errors = _axis_errors(space, plan).reshape(-1, 2).max(axis=1)
    axes = [int(k) for k in np.argsort(-errors, kind="stable") if errors[k] > _FOLLOW_ERROR]
    if not axes or len(axes) == plan.ndim:
        return None
    paths = [_marched_path(space, plan, k, [a for a in axes if a != k]) for k in axes]
    if any(p is None for p in paths):
        return None
    # not-a-knot ends: a path that still curves at the outer nodes (y − κx² − cx³) is not
    # straightened there, as natural ends would
    bend = CurveBend(tuple(axes), _follow_nodes(), np.array(paths), ends="not-a-knot")
    base = {f.name: getattr(plan, f.name) for f in fields(Reparameterization)}
    candidate = BentCoordinatesPlan(
        **{**base, "kind": f"followed-{plan.kind}"}, inner=plan, bend=bend
    )
    score = _gaussian_score(space, candidate)
    if not score < plan.gaussian_score:
        return None
    return replace(candidate, gaussian_score=score)


#: an axis is light-tailed when its log density drops more than this at ±3 sd (mean of the
#: two sides; 4.5 for a Gaussian)
_LIGHT_DROP = 9.0


def _drops(space: ValueSpace, plan: Reparameterization, k: int, at: float = 3.0) -> float:
    """Mean drop of the log density at ``z_k = ±at`` (the others at 0)."""
    base, _ = plan.logp_dlogp(space, np.zeros(plan.ndim), safe=True)
    drops = []
    for sign in (-at, at):
        z = np.zeros(plan.ndim)
        z[k] = sign
        with np.errstate(all="ignore"):
            logp, _ = plan.logp_dlogp(space, z, safe=True)
        drops.append(base - logp if np.isfinite(logp) else np.inf)
    return float(np.mean(drops))


def _squeezed_plan(space: ValueSpace, plan: BentPlan, inverse: np.ndarray) -> BentPlan:
    """``plan`` with its light-tailed axes squeezed (β fitted to a drop of 4.5 at ±3)."""
    light = [k for k in range(plan.ndim) if _LIGHT_DROP < _drops(space, plan, k) < np.inf]
    if not light:
        return plan
    beta = np.zeros(len(light))

    def with_beta(values):
        squeeze = Squeeze(plan.mean.copy(), inverse[light], plan.chol[:, light], values)
        return replace(plan, squeeze=squeeze)

    for j, k in enumerate(light):

        def excess(log_beta, j=j, k=k):
            trial = beta.copy()
            trial[j] = np.exp(log_beta)
            return _drops(space, with_beta(trial), k) - 4.5

        if excess(np.log(1e-4)) > 0 > excess(np.log(1e2)):
            beta[j] = np.exp(optimize.brentq(excess, np.log(1e-4), np.log(1e2), xtol=1e-3))
    keep = beta > 0
    if not keep.any():
        return plan
    light = [k for k, kept in zip(light, keep, strict=True) if kept]
    squeezed = replace(
        plan,
        squeeze=Squeeze(plan.mean.copy(), inverse[light], plan.chol[:, light], beta[keep]),
    )
    score = _gaussian_score(space, squeezed)
    if score > plan.gaussian_score + 0.1:
        return plan
    return replace(squeezed, gaussian_score=score, kind=f"squeezed-{plan.kind}")
