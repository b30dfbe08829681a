"""kohpymc.kronecker: grid/Kronecker GP algebra against dense references."""

from __future__ import annotations

import numpy as np
import pytensor
import pytensor.tensor as pt
import pytest
from scipy.stats import multivariate_normal, norm

from kohpymc.kronecker import (
    KronSolver,
    grid_layout,
    grid_loo_log_density,
    kron_gp_loglik,
)

SEED = 53
AXES = (np.array([0.0, 1.0]), np.array([0.0, 0.4, 1.1]))


def _grid_points(axes):
    return np.array(np.meshgrid(*axes, indexing="ij")).reshape(len(axes), -1).T


def _dense_cov(X, eta, ls, noise_var, c):
    K = np.ones((len(X), len(X)))
    for k in range(X.shape[1]):
        K *= np.exp(-0.5 * (X[:, k, None] - X[None, :, k]) ** 2 / ls[k] ** 2)
    return eta**2 * K + c + noise_var * np.eye(len(X))


@pytest.mark.parametrize("c", [0.0, 0.7])
def test_kron_loglik_and_gradient_match_dense(c):
    rng = np.random.default_rng(SEED)
    X = _grid_points(AXES)
    R_val = rng.normal(size=(2, 3))
    eta_val, ls_val, s2 = 1.3, np.array([0.8, 0.5]), 0.2

    R, eta, ls = pt.dmatrix("R"), pt.dscalar("eta"), pt.dvector("ls")
    ll = kron_gp_loglik(R, AXES, eta, ls, s2, c)
    fn = pytensor.function([R, eta, ls], [ll, *pt.grad(ll, [R, eta, ls])])
    value, g_R, g_eta, g_ls = fn(R_val, eta_val, ls_val)

    def dense(eta_, ls_, R_=R_val):
        cov = _dense_cov(X, eta_, ls_, s2, c)
        return multivariate_normal(np.zeros(len(X)), cov).logpdf(R_.ravel())

    np.testing.assert_allclose(value, dense(eta_val, ls_val), rtol=1e-10)
    h = 1e-6
    fd_eta = (dense(eta_val + h, ls_val) - dense(eta_val - h, ls_val)) / (2 * h)
    np.testing.assert_allclose(g_eta, fd_eta, rtol=1e-6)
    for k in range(2):
        e = np.eye(2)[k] * h
        fd = (dense(eta_val, ls_val + e) - dense(eta_val, ls_val - e)) / (2 * h)
        np.testing.assert_allclose(g_ls[k], fd, rtol=1e-6)
    cov = _dense_cov(X, eta_val, ls_val, s2, c)
    np.testing.assert_allclose(g_R.ravel(), -np.linalg.solve(cov, R_val.ravel()), rtol=1e-8)


@pytest.mark.parametrize("c", [0.0, 0.5])
def test_solver_matches_dense_solve(c):
    rng = np.random.default_rng(SEED + 1)
    X = _grid_points(AXES)
    B = rng.normal(size=(2, 2, 3))
    ls = np.array([0.9, 0.6])
    solver = KronSolver(AXES, 1.1, ls, 0.3, c)
    cov = _dense_cov(X, 1.1, ls, 0.3, c)
    out = solver.solve(B).eval().reshape(2, -1)
    np.testing.assert_allclose(out, np.linalg.solve(cov, B.reshape(2, -1).T).T, rtol=1e-8)
    Xn = np.array([[0.2, 0.3], [1.5, -0.1]])
    cross = solver.cross([Xn[:, 0], Xn[:, 1]]).eval().reshape(2, -1)
    dense_cross = _dense_cov(np.vstack([Xn, X]), 1.1, ls, 0.0, 0.0)[:2, 2:]
    np.testing.assert_allclose(cross, dense_cross, rtol=1e-10)


@pytest.mark.parametrize("c", [0.0, 0.4])
def test_grid_loo_matches_brute_force_conditionals(c):
    rng = np.random.default_rng(SEED + 2)
    r = 2
    X = np.repeat(_grid_points(AXES), r, axis=0)
    perm = rng.permutation(len(X))  # rows in any order
    X = X[perm]
    y, mu = rng.normal(size=len(X)), rng.normal(scale=0.1, size=len(X))
    eta, ls, v = 0.9, np.array([0.7, 0.4]), 0.25
    layout = grid_layout(X, ["a", "b"])
    out = grid_loo_log_density(y, mu, eta, ls, layout, v, c)

    cov = _dense_cov(X, eta, ls, 0.0, c) + v * np.eye(len(X))
    expected = []
    for i in range(len(X)):
        rest = np.arange(len(X)) != i
        w = np.linalg.solve(cov[np.ix_(rest, rest)], cov[rest, i])
        mean = mu[i] + w @ (y[rest] - mu[rest])
        var = cov[i, i] - cov[i, rest] @ w
        expected.append(norm.logpdf(y[i], mean, np.sqrt(var)))
    np.testing.assert_allclose(out, expected, rtol=1e-8)


def test_grid_layout_orders_rows_and_rejects_bad_grids():
    X = np.array([[1.0, 0.0], [0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0], [1.0, 0.0]])
    with pytest.raises(ValueError, match="not on a full grid"):
        grid_layout(X[:3], ["a", "b"])
    with pytest.raises(ValueError, match="unequal replicates"):
        grid_layout(X, ["a", "b"])
    layout = grid_layout(np.vstack([X[:4], X[:4]]), ["a", "b"])
    assert layout.shape == (2, 2) and layout.size == 4 and layout.replicates == 2
    sorted_rows = np.vstack([X[:4], X[:4]])[layout.order]
    np.testing.assert_array_equal(sorted_rows[::2], sorted_rows[1::2])
    np.testing.assert_array_equal(sorted_rows[::2], _grid_points(layout.axes))
