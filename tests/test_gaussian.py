import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import pytest
from scipy.stats import multivariate_normal

from kohpymc.gaussian import GaussianLikelihood, GaussianLogDensity


def _spd(n, seed):
    a = np.random.default_rng(seed).normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


@pytest.fixture(scope="module")
def functions():
    r, C = pt.dvector("r"), pt.dmatrix("C")
    logp = GaussianLogDensity()(r, C)[0]
    grads = pytensor.grad(logp, [r, C])
    # reference: PyMC's MvNormal log density and its autodiff gradient
    ref = pm.logp(pm.MvNormal.dist(mu=pt.zeros_like(r), cov=C), r)
    ref_grads = pytensor.grad(ref, [r, C])
    return (
        pytensor.function([r, C], [logp, *grads]),
        pytensor.function([r, C], [logp, *grads], mode="NUMBA"),
        pytensor.function([r, C], [ref, *ref_grads]),
    )


@pytest.mark.parametrize("n", [1, 3, 20])
def test_value_and_gradient_match_pymc_mvnormal(functions, n):
    fast, numba, reference = functions
    C, r = _spd(n, n), np.random.default_rng(100 + n).normal(size=n)
    expected = reference(r, C)
    np.testing.assert_allclose(expected[0], multivariate_normal(np.zeros(n), C).logpdf(r))
    for got in (fast(r, C), numba(r, C)):
        np.testing.assert_allclose(got[0], expected[0], rtol=1e-12)
        np.testing.assert_allclose(got[1], expected[1], rtol=1e-10, atol=1e-12)
        # PyMC's gradient in C is lower-triangular, ours symmetric: both give the same
        # derivative along every symmetric perturbation, i.e. the same g + gᵀ
        np.testing.assert_allclose(
            got[2] + got[2].T, expected[2] + expected[2].T, rtol=1e-10, atol=1e-12
        )


def test_gradient_matches_finite_differences(functions):
    fast = functions[0]
    C, r = _spd(4, 7), np.random.default_rng(8).normal(size=4)
    _, g_r, g_C = fast(r, C)
    h = 1e-6
    for i in range(4):
        e = np.zeros(4)
        e[i] = h
        fd = (fast(r + e, C)[0] - fast(r - e, C)[0]) / (2 * h)
        np.testing.assert_allclose(g_r[i], fd, rtol=1e-7)
    for i, j in [(1, 3), (2, 2)]:  # covariances are symmetric: perturb C_ij and C_ji
        E = np.zeros((4, 4))
        E[i, j] = E[j, i] = h
        fd = (fast(r, C + E)[0] - fast(r, C - E)[0]) / (2 * h)
        np.testing.assert_allclose(np.sum(g_C * E) / h, fd, rtol=1e-6)


def test_not_positive_definite_gives_minus_infinity(functions):
    fast, numba, _ = functions
    for f in (fast, numba):
        assert f(np.ones(3), -np.eye(3))[0] == -np.inf
        assert f(np.ones(3), np.full((3, 3), np.nan))[0] == -np.inf


def test_likelihood_in_a_model_matches_mvnormal():
    y = np.array([0.3, -0.1, 0.8, 0.2])
    x = np.linspace(0, 1, 4)
    models = []
    for dist in (GaussianLikelihood, pm.MvNormal):
        with pm.Model() as model:
            eta = pm.HalfNormal("eta")
            ls = pm.Gamma("ls", 2, 2)
            cov = eta**2 * pm.gp.cov.ExpQuad(1, ls)(x[:, None]) + 0.1 * pt.eye(4)
            dist("y", mu=pt.zeros(4), cov=cov, observed=y)
        models.append(model)
    point = {"eta_log__": np.array(0.2), "ls_log__": np.array(-0.4)}
    fast, ref = (m.compile_logp() for m in models)
    dfast, dref = (m.compile_dlogp() for m in models)
    np.testing.assert_allclose(fast(point), ref(point), rtol=1e-12)
    np.testing.assert_allclose(dfast(point), dref(point), rtol=1e-9)
    assert isinstance(models[0]["y"].owner.op, type(models[1]["y"].owner.op))
