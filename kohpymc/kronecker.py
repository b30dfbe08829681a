r"""Exact Gaussian-process algebra on a full grid with replicates (Kronecker structure).

When the rows of a data set, restricted to the kernel inputs, lie on a full grid (every
combination of the unique values of each input) with the same number ``r`` of replicates
per grid point, the stationary squared-exponential GP has an exact likelihood that never
forms the ``n × n`` covariance.  This module holds that linear algebra; the formulation
that uses it is :class:`~kohpymc.discrepancy.grid.GridGP`.

1. **Replicate reduction.**  With ``ȳ``, ``Ḡ`` the replicate means on the ``m = n / r``
   grid points and ``s² = σ²/r``,
   ``p(y) = N(ȳ | Ḡ + m0, K + c 11ᵀ + s² I) · C``,
   ``log C = Σ_u [-(r-1)/2 log(2πσ²) - ½ log r - S_u / (2σ²)]`` with ``S_u`` the
   within-replicate sum of squares of the residual.
2. **Kronecker.**  ``K = η² ⊗_k K_k(ℓ_k)``; with ``K_k = Q_k diag(λ_k) Q_kᵀ`` the solve
   and the log-determinant of ``K + s² I`` are diagonal in the basis ``⊗_k Q_k``.  A
   constant of prior variance ``c`` added to every point is a rank-one update
   (Sherman–Morrison and the matrix-determinant lemma).
3. **Gradient.**  :func:`kron_gp_loglik` is an inlined ``OpFromGraph`` whose
   ``lop_overrides`` give the analytic gradient
   ``½ (α'ᵀ ∂K α' - tr((K' + s² I)⁻¹ ∂K))`` in the eigenbasis, so PyTensor never
   differentiates through ``eigh``.
4. **Leave-one-out.**  :func:`grid_loo_log_density` gives ``log p(y_i | y_-i)`` of every
   raw row (numpy, Woodbury in the eigenbasis).

:class:`GridLayout` / :func:`grid_layout` check and sort the rows; :class:`KronSolver`
gives forward-only solves and cross-covariances for prediction.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pytensor.tensor as pt
from pytensor.compile.builders import OpFromGraph

__all__ = [
    "GridLayout",
    "KronSolver",
    "grid_layout",
    "grid_loo_log_density",
    "kron_gp_loglik",
]

_LOG_2PI = float(np.log(2.0 * np.pi))


class GridLayout:
    """Rows of a data set arranged as a full grid with ``r`` replicates per point.

    Attributes
    ----------
    axes : tuple of ndarray
        Sorted unique values of each kernel input.
    order : ndarray
        Row permutation: ``X[order]`` is in grid (C) order, replicates last.
    replicates : int
        Replicates per grid point.

    Examples
    --------
    >>> import numpy as np
    >>> X = np.array([[1.0, 0.0], [0.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    >>> layout = grid_layout(X, ["a", "b"])
    >>> layout.shape, layout.replicates
    ((2, 2), 1)
    """

    def __init__(self, axes: tuple[np.ndarray, ...], order: np.ndarray, replicates: int):
        self.axes = axes
        self.order = order
        self.replicates = replicates

    @property
    def shape(self) -> tuple[int, ...]:
        """Number of unique values per kernel input."""
        return tuple(len(a) for a in self.axes)

    @property
    def size(self) -> int:
        """Number of grid points ``m``."""
        return int(np.prod(self.shape))


def grid_layout(X: np.ndarray, names: Sequence[str]) -> GridLayout:
    """Check that the rows of ``X`` form a full grid with equal replicates; sort them.

    Parameters
    ----------
    X : ndarray, shape (n, d)
        Kernel-input columns.
    names : sequence of str
        Their names (for messages).

    Returns
    -------
    GridLayout

    Raises
    ------
    ValueError
        If a combination of the unique values is missing or the grid points have
        unequal numbers of replicates.

    Examples
    --------
    >>> import numpy as np
    >>> grid_layout(np.array([[0.0], [1.0], [0.0], [1.0]]), ["x"]).replicates
    2
    """
    X = np.asarray(X, dtype=float)
    axes, index = [], []
    for k in range(X.shape[1]):
        values, inverse = np.unique(X[:, k], return_inverse=True)
        axes.append(values)
        index.append(inverse.reshape(-1))
    shape = tuple(len(a) for a in axes)
    cell = np.ravel_multi_index(tuple(index), shape)
    counts = np.bincount(cell, minlength=int(np.prod(shape)))
    if np.any(counts == 0):
        raise ValueError(
            f"GridGP: the data are not on a full grid of {list(names)}: "
            f"{int(np.sum(counts == 0))} of {counts.size} combinations of the unique "
            f"values {dict(zip(names, shape, strict=True))} have no row"
        )
    if np.any(counts != counts[0]):
        raise ValueError(
            f"GridGP: unequal replicates per grid point of {list(names)} "
            f"(between {int(counts.min())} and {int(counts.max())} rows); every point "
            "needs the same number"
        )
    order = np.argsort(cell, kind="stable")
    return GridLayout(tuple(axes), order, int(counts[0]))


# --------------------------------------------------------------------------- algebra


def _se(x: np.ndarray, ls: Any) -> tuple[Any, np.ndarray]:
    d2 = (x[:, None] - x[None, :]) ** 2
    return pt.exp(-0.5 * d2 / ls**2), d2


def _mode_mult(X: Any, mats: Sequence[Any]) -> Any:
    """``X ×_k M_kᵀ`` for every axis k (``tensordot`` cycles the axes back to order)."""
    for M in mats:
        X = pt.tensordot(X, M, axes=[[0], [0]])
    return X


def _outer(vectors: Sequence[Any]) -> Any:
    out = vectors[0]
    for v in vectors[1:]:
        out = out[..., None] * v
    return out


def _kron_parts(
    R: Any, eta: Any, ls: Any, axes: tuple[np.ndarray, ...], noise_var: float, c: float
) -> tuple[Any, Any, Any, Any]:
    """``(L, ∂L/∂R, ∂L/∂η, ∂L/∂ℓ)`` of ``log N(vec R | 0, η² ⊗K_k + c 11ᵀ + s² I)``."""
    d = len(axes)
    kernels = [_se(g, ls[k]) for k, g in enumerate(axes)]
    Ks = [K for K, _ in kernels]
    eig = [pt.linalg.eigh(K) for K in Ks]
    lam = [w for w, _ in eig]
    Qs = [v for _, v in eig]
    lam_all = eta**2 * _outer(lam)
    D = lam_all + noise_var
    Rt = _mode_mult(R, Qs)  # R in the eigenbasis
    At = Rt / D  # (K + s² I)⁻¹ R in the eigenbasis
    m = int(np.prod([len(g) for g in axes]))
    quad = pt.sum(Rt * At)
    logdet = pt.sum(pt.log(D))
    trace_eta = pt.sum(lam_all / D)
    if c > 0:
        Ot = _outer([pt.sum(Q, axis=0) for Q in Qs])  # 1 in the eigenbasis
        Bt = Ot / D  # b = (K + s² I)⁻¹ 1
        beta = pt.sum(Ot * Bt)
        gamma = pt.sum(Rt * Bt)
        denom = 1.0 + c * beta
        quad = quad - c * gamma**2 / denom
        logdet = logdet + pt.log(denom)
        At = At - (c * gamma / denom) * Bt  # α' = (K + c 11ᵀ + s² I)⁻¹ R
        trace_eta = trace_eta - (c / denom) * pt.sum(Bt**2 * lam_all)
    value = -0.5 * (quad + logdet + m * _LOG_2PI)
    alpha = _mode_mult(At, [Q.T for Q in Qs])

    # ∂L/∂p = ½ (α'ᵀ ∂K α' - tr((K' + s² I)⁻¹ ∂K)); ∂K/∂η = 2K/η
    g_eta = (pt.sum(At**2 * lam_all) - trace_eta) / eta
    g_ls = []
    for k in range(d):
        dK = Ks[k] * kernels[k][1] / ls[k] ** 3  # ∂K_k/∂ℓ_k = K_k ∘ Δ²/ℓ³
        mats = [dK if j == k else Ks[j] for j in range(d)]
        c_k = pt.sum(Qs[k] * pt.dot(dK, Qs[k]), axis=0)  # diag(Q_kᵀ ∂K_k Q_k)
        trace = pt.sum(_outer([c_k if j == k else lam[j] for j in range(d)]) / D)
        if c > 0:
            b = _mode_mult(Bt, [Q.T for Q in Qs])
            trace = trace - (c / denom) * pt.sum(b * _mode_mult(b, mats))
        quad_k = pt.sum(alpha * _mode_mult(alpha, mats))
        g_ls.append(0.5 * eta**2 * (quad_k - trace))
    return value, -alpha, g_eta, pt.stack(g_ls)


def kron_gp_loglik(
    R: Any, axes: tuple[np.ndarray, ...], eta: Any, ls: Any, noise_var: float, c: float = 0.0
) -> pt.TensorVariable:
    """``log N(vec R | 0, η² ⊗_k K_k(ℓ_k) + c 11ᵀ + s² I)`` with its analytic gradient.

    Parameters
    ----------
    R : TensorVariable
        Residual on the grid, shape ``(len(a) for a in axes)``.
    axes : tuple of ndarray
        1-D input axis per kernel factor (squared-exponential on each).
    eta, ls : TensorVariable
        Amplitude η and one length scale per factor.
    noise_var : float
        ``s²``.
    c : float
        Variance of a constant added to every point (an integrated-out intercept).

    Returns
    -------
    TensorVariable
        The log density, an inlined ``OpFromGraph`` whose ``lop_overrides`` returns the
        analytic gradients (no gradient through ``eigh``).

    Examples
    --------
    >>> import numpy as np
    >>> axes = (np.array([0.0, 1.0]), np.array([0.0, 0.5, 1.0]))
    >>> R = np.arange(6.0).reshape(2, 3) / 6
    >>> val = kron_gp_loglik(R, axes, 1.0, np.array([1.0, 1.0]), 0.1).eval()
    >>> X = np.array([[a, b] for a in axes[0] for b in axes[1]])
    >>> K = np.exp(-0.5 * ((X[:, None] - X[None]) ** 2).sum(-1)) + 0.1 * np.eye(6)
    >>> from scipy.stats import multivariate_normal
    >>> bool(np.isclose(val, multivariate_normal(np.zeros(6), K).logpdf(R.ravel())))
    True
    """
    c = float(c)
    d = len(axes)
    R_in = pt.tensor("R", shape=(None,) * d, dtype="float64")
    eta_in = pt.scalar("eta", dtype="float64")
    ls_in = pt.vector("ls", dtype="float64")
    outs = _kron_parts(R_in, eta_in, ls_in, axes, noise_var, c)

    def lop(inputs: list[Any], outputs: list[Any], output_grads: list[Any]) -> list[Any]:
        (gz,) = output_grads
        return [gz * g for g in _kron_parts(*inputs[:3], axes, noise_var, c)[1:]]

    op = OpFromGraph([R_in, eta_in, ls_in], [outs[0]], lop_overrides=lop, inline=True)
    R = pt.as_tensor_variable(R, dtype="float64")
    ls = pt.as_tensor_variable(ls, dtype="float64")
    return op(R, pt.as_tensor_variable(eta, dtype="float64"), ls)


class KronSolver:
    """Forward-only solves with ``K + c 11ᵀ + s² I`` on the grid (no gradients needed).

    ``K = η² ⊗_k K_k(ℓ_k)`` (squared-exponential factors), solved in the eigenbasis of
    the factors as in :func:`kron_gp_loglik`; used for predictions of
    :class:`~kohpymc.discrepancy.grid.GridGP`.

    Parameters
    ----------
    axes : tuple of ndarray
        1-D input axis per kernel factor.
    eta, ls : TensorVariable
        Amplitude η and one length scale per factor.
    noise_var : float
        ``s²``.
    c : float
        Variance of a constant added to every point (0 for none).

    Examples
    --------
    >>> import numpy as np
    >>> axes = (np.array([0.0, 1.0]), np.array([0.0, 0.5, 1.0]))
    >>> solver = KronSolver(axes, 1.0, np.array([1.0, 1.0]), 0.1, 0.0)
    >>> R = np.arange(6.0).reshape(1, 2, 3)
    >>> X = np.array([[a, b] for a in axes[0] for b in axes[1]])
    >>> K = np.exp(-0.5 * ((X[:, None] - X[None]) ** 2).sum(-1)) + 0.1 * np.eye(6)
    >>> bool(np.allclose(solver.solve(R).eval().ravel(), np.linalg.solve(K, R.ravel())))
    True
    """

    def __init__(
        self, axes: tuple[np.ndarray, ...], eta: Any, ls: Any, noise_var: float, c: float
    ) -> None:
        self.axes, self.eta, self.ls, self.c = axes, eta, ls, c
        eig = [pt.linalg.eigh(_se(g, ls[k])[0]) for k, g in enumerate(axes)]
        self.Qs = [v for _, v in eig]
        self.D = eta**2 * _outer([w for w, _ in eig]) + noise_var
        if c > 0:
            self.b = self._solve0(pt.ones((1, *(len(a) for a in axes))))[0]
            self.beta = pt.sum(self.b)

    def _solve0(self, X):
        """``(K + s² I)⁻¹`` applied to each ``X[p]`` (shape ``(p, *grid)``)."""
        Xt = X
        for Q in self.Qs:  # axis 1 onwards, batch axis stays first
            Xt = pt.tensordot(Xt, Q, axes=[[1], [0]])
        Xt = Xt / self.D
        for Q in self.Qs:
            Xt = pt.tensordot(Xt, Q.T, axes=[[1], [0]])
        return Xt

    def solve(self, X):
        """``(K + c 11ᵀ + s² I)⁻¹`` applied to each ``X[p]``."""
        out = self._solve0(X)
        if self.c > 0:
            d = len(self.axes)
            ones_dot = pt.sum(out, axis=tuple(range(1, d + 1)))  # 1ᵀ A⁻¹ X_p
            scale = self.c * ones_dot / (1.0 + self.c * self.beta)
            out = out - scale[(slice(None),) + (None,) * d] * self.b
        return out

    def cross(self, Xn_cols: list[Any]):
        """``K(X_new, grid)`` shaped ``(p, *grid)`` (without the constant term)."""
        factors = []
        d = len(self.axes)
        for k, (g, x) in enumerate(zip(self.axes, Xn_cols, strict=True)):
            kk = pt.exp(-0.5 * (x[:, None] - g[None, :]) ** 2 / self.ls[k] ** 2)
            index = [slice(None)] + [None] * d
            index[k + 1] = slice(None)
            factors.append(kk[tuple(index)])
        out = self.eta**2 * factors[0]
        for f in factors[1:]:
            out = out * f
        return out


def _np_mode_mult(X: np.ndarray, mats: Sequence[np.ndarray]) -> np.ndarray:
    for M in mats:
        X = np.tensordot(X, M, axes=([0], [0]))
    return X


def _np_outer(vectors: Sequence[np.ndarray]) -> np.ndarray:
    out = vectors[0]
    for v in vectors[1:]:
        out = out[..., None] * v
    return out


def grid_loo_log_density(
    y: np.ndarray,
    mu: np.ndarray,
    eta: float,
    ls: np.ndarray,
    layout: GridLayout,
    noise_var: float,
    c: float = 0.0,
) -> np.ndarray:
    """``log p(y_i | y_-i)`` of every raw row under the replicated Kronecker GP.

    The raw covariance is ``C = P K' Pᵀ + v I`` (``P`` maps grid points to their rows,
    ``K' = η² ⊗K_k + c 11ᵀ``, ``v`` the noise variance).  With ``s² = v/r`` and
    ``A' = K' + s² I``, Woodbury gives ``C⁻¹ = (I - P (I - s² A'⁻¹) Pᵀ / r) / v``, so
    ``[C⁻¹]_ii = (1 - (1 - s² [A'⁻¹]_uu) / r) / v`` and
    ``[C⁻¹ (y - μ)]_i = (e_i - ē_u + s² [A'⁻¹ ē]_u) / v`` for row ``i`` at point ``u``
    (``e = y - μ``, ``ē`` its replicate means); both come from the eigenbasis.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc.loo import gaussian_loo_log_density
    >>> X = np.array([[0.0], [1.0], [0.0], [1.0]]); y = np.array([0.1, 0.5, -0.2, 0.7])
    >>> layout = grid_layout(X, ["x"])
    >>> C = np.exp(-0.5 * (X - X.T) ** 2) + 0.3 * np.eye(4)
    >>> out = grid_loo_log_density(y, np.zeros(4), 1.0, np.array([1.0]), layout, 0.3)
    >>> bool(np.allclose(out, gaussian_loo_log_density(y, np.zeros(4), C)))
    True
    """
    shape, r, order = layout.shape, layout.replicates, layout.order
    s2 = noise_var / r
    eig = [
        np.linalg.eigh(np.exp(-0.5 * (g[:, None] - g[None, :]) ** 2 / ls[k] ** 2))
        for k, g in enumerate(layout.axes)
    ]
    Qs = [Q for _, Q in eig]
    D = eta**2 * _np_outer([w for w, _ in eig]) + s2

    def solve0(X: np.ndarray) -> np.ndarray:
        return _np_mode_mult(_np_mode_mult(X, Qs) / D, [Q.T for Q in Qs])

    E = (np.asarray(y, dtype=float) - mu)[order].reshape((*shape, r))
    Ebar = E.mean(axis=-1)
    a = solve0(Ebar)
    diag = _np_mode_mult(1.0 / D, [(Q * Q).T for Q in Qs])  # diag((K + s² I)⁻¹)
    if c > 0:
        b = solve0(np.ones(shape))
        denom = 1.0 + c * b.sum()
        a = a - c * b * a.sum() / denom
        diag = diag - c * b**2 / denom
    precision = (1.0 - (1.0 - s2 * diag) / r) / noise_var
    alpha = (E - Ebar[..., None] + s2 * a[..., None]) / noise_var
    values = 0.5 * (
        np.log(precision)[..., None] - np.log(2 * np.pi) - alpha**2 / precision[..., None]
    )
    out = np.empty(values.size)
    out[order] = values.reshape(-1)
    return out
