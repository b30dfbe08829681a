"""MAP, Laplace covariance and over-dispersed starting points of a numpy log density."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize

__all__ = ["find_starts"]


def find_starts(
    logp: Callable[[np.ndarray], float],
    init: np.ndarray,
    chains: int,
    seed: int,
    *,
    spread: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MAP, a Laplace covariance and over-dispersed chain starting points.

    The MAP is found with BFGS (then Nelder–Mead from there) on ``-logp`` from ``init``;
    the covariance is the inverse of the central-difference Hessian there, with
    eigenvalues clipped to variances in ``[1e-10, 4]`` (flat or non-concave directions
    get sd 2).  Chain ``c`` starts at ``MAP + spread · chol(cov) · z_c``, ``z_c`` standard
    normal, redrawn (with halved spread) until ``logp`` is finite.

    Parameters
    ----------
    logp : callable
        Log density of a 1-D vector.
    init : numpy.ndarray
        Where the optimisation starts.
    chains : int
        Number of starting points.
    seed : int
        Seed of the jitter.
    spread : float
        Jitter in units of the Laplace standard deviations.

    Returns
    -------
    starts : numpy.ndarray
        ``(chains, d)`` starting points.
    mode : numpy.ndarray
        The MAP.
    cov : numpy.ndarray
        ``(d, d)`` Laplace covariance (also a good initial proposal covariance).
    """

    def neg(v: np.ndarray) -> float:
        try:
            value = logp(v)
        except ArithmeticError:
            return 1e300
        return -value if np.isfinite(value) else 1e300

    init = np.asarray(init, dtype=float)
    res = minimize(neg, init, method="BFGS")
    res = minimize(neg, res.x, method="Nelder-Mead", options={"xatol": 1e-8, "fatol": 1e-10})
    mode = res.x
    d = mode.size
    h = 1e-4
    H = np.empty((d, d))
    f0 = neg(mode)
    eye = np.eye(d) * h
    for i in range(d):
        for j in range(i, d):
            if i == j:
                H[i, i] = (neg(mode + eye[i]) - 2 * f0 + neg(mode - eye[i])) / h**2
            else:
                pp = neg(mode + eye[i] + eye[j])
                pm_ = neg(mode + eye[i] - eye[j])
                mp = neg(mode - eye[i] + eye[j])
                mm = neg(mode - eye[i] - eye[j])
                H[i, j] = H[j, i] = (pp - pm_ - mp + mm) / (4 * h**2)
    lam, V = np.linalg.eigh(H)
    var = np.clip(1.0 / np.where(lam > 0, lam, 1e-300), 1e-10, 4.0)
    cov = (V * var) @ V.T
    chol = np.linalg.cholesky(cov)
    rng = np.random.default_rng([seed, 7919])
    starts = np.empty((chains, d))
    for c in range(chains):
        scale = spread
        for _ in range(60):
            cand = mode + scale * chol @ rng.standard_normal(d)
            if neg(cand) < 1e300:
                break
            scale *= 0.5
        else:  # pragma: no cover - the mode itself is finite
            cand = mode.copy()
        starts[c] = cand
    return starts, mode, cov
