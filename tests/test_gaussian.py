import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import pytest
from scipy import linalg
from scipy.stats import multivariate_normal

from kohpymc.gaussian import (
    GaussianLikelihood,
    GaussianLogDensity,
    add_to_covariance,
    covariance_solve,
    low_rank_covariance,
    low_rank_parts,
    woodbury_log_density,
)


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


# 240: past LAPACK's block size, where dpotri takes its blocked path (a GP over the
# dielectric example's calibration rows)
@pytest.mark.parametrize("n", [1, 3, 20, 240])
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


# ---------------------------------------------------------------- diagonal plus low rank
def _low_rank_instance(n, k, seed, spread=0.0):
    """``r``, ``d``, ``F`` with ``d`` spanning ``±spread`` decades."""
    rng = np.random.default_rng(seed)
    d = 10.0 ** rng.uniform(-spread, spread, n) if spread else rng.uniform(0.5, 2.0, n)
    return rng.normal(size=n), d, rng.normal(size=(n, k))


def _value_and_gradient(log_density, mode=None):
    """``(r, d, F) -> (log p, ∂r, ∂d, ∂F)`` compiled in ``mode``, from a graph of its own.

    One graph per mode: the gradient of a Cholesky holds ``AllocDiag`` nodes whose inner
    graph a NUMBA compilation rewrites in place, which breaks a C-mode function of the
    same graph that had not run yet (PyTensor 2.38).
    """
    r, d, F = pt.dvector("r"), pt.dvector("d"), pt.dmatrix("F")
    logp = log_density(r, d, F)
    return pytensor.function([r, d, F], [logp, *pytensor.grad(logp, [r, d, F])], mode=mode)


def _dense_reference(r, d, F):
    """PyMC's MvNormal on the dense matrix, differentiated through it."""
    return pm.logp(pm.MvNormal.dist(mu=pt.zeros_like(r), cov=pt.diag(d) + F @ F.T), r)


def _scipy_log_density(r, C):
    """``log N(r; 0, C)`` by SciPy's Cholesky (``multivariate_normal`` refuses C's conditioning)."""
    chol, lower = linalg.cho_factor(C, lower=True)
    quad = r @ linalg.cho_solve((chol, lower), r)
    return -0.5 * (quad + 2.0 * np.sum(np.log(np.diag(chol))) + len(r) * np.log(2.0 * np.pi))


@pytest.fixture(scope="module")
def low_rank_functions():
    return (
        _value_and_gradient(woodbury_log_density),
        _value_and_gradient(woodbury_log_density, mode="NUMBA"),
        _value_and_gradient(_dense_reference),
    )


@pytest.mark.parametrize(
    ("n", "k", "spread"),
    [
        (2, 1, 0.0),
        (12, 1, 0.0),
        (12, 11, 0.0),
        (40, 5, 0.0),
        (40, 5, 6.0),
        (40, 1, 6.0),
        # k = n - 1 with d over 2·4 decades: ∂/∂d agrees to ~2e-8 only (cancellation in
        # the Woodbury form; against exact rational arithmetic the error is 5e-9)
        (12, 11, 3.0),
    ],
)
def test_woodbury_matches_the_dense_mvnormal(low_rank_functions, n, k, spread):
    fast, numba, reference = low_rank_functions
    r, d, F = _low_rank_instance(n, k, seed=10 * n + k, spread=spread)
    expected = reference(r, d, F)
    np.testing.assert_allclose(expected[0], _scipy_log_density(r, np.diag(d) + F @ F.T), rtol=1e-8)
    for got in (fast(r, d, F), numba(r, d, F)):
        for value, ref in zip(got, expected, strict=True):
            scale = np.max(np.abs(ref))  # relative to the largest entry of each gradient
            np.testing.assert_allclose(value, ref, rtol=1e-8, atol=1e-8 * scale)


def test_woodbury_gives_minus_infinity_for_a_non_positive_diagonal(low_rank_functions):
    r, d, F = _low_rank_instance(5, 2, seed=3)
    d[2] = -1.0
    for f in low_rank_functions[:2]:
        assert f(r, d, F)[0] == -np.inf


def test_low_rank_covariance_is_the_dense_matrix_with_its_gradient():
    d, F = pt.dvector("d"), pt.dmatrix("F")
    w = pt.dmatrix("w")  # a generic cotangent
    outputs = []
    for C in (low_rank_covariance(d, F), pt.diag(d) + F @ F.T):
        loss = pt.sum(w * C)
        outputs.append([C, *pytensor.grad(loss, [d, F])])
    _, dv, Fv = _low_rank_instance(6, 2, seed=4)
    wv = np.random.default_rng(5).normal(size=(6, 6))
    ref = pytensor.function([d, F, w], outputs[1])(dv, Fv, wv)
    for mode in ("FAST_RUN", "NUMBA"):
        got = pytensor.function([d, F, w], outputs[0], mode=mode)(dv, Fv, wv)
        for value, expected in zip(got, ref, strict=True):
            np.testing.assert_allclose(value, expected, rtol=1e-12, atol=1e-12)


def test_add_to_covariance_keeps_the_structure_and_solves_by_woodbury():
    _, d, F = _low_rank_instance(8, 2, seed=6)
    B = np.random.default_rng(7).normal(size=(8, 1))
    C = add_to_covariance(low_rank_covariance(d, F), diagonal=0.3, factor=B)
    dense = np.diag(d + 0.3) + F @ F.T + B @ B.T
    assert low_rank_parts(C)[1].eval().shape == (8, 3)
    np.testing.assert_allclose(C.eval(), dense, rtol=1e-12)
    plain = add_to_covariance(pt.as_tensor(np.diag(d)), diagonal=0.3, factor=B)
    assert low_rank_parts(plain) is None
    np.testing.assert_allclose(plain.eval(), np.diag(d + 0.3) + B @ B.T, rtol=1e-12)
    rhs = np.random.default_rng(8).normal(size=(8, 2))
    for cov in (C, pt.as_tensor(dense)):
        np.testing.assert_allclose(covariance_solve(cov, rhs).eval(), np.linalg.solve(dense, rhs))
        np.testing.assert_allclose(
            covariance_solve(cov, rhs[:, 0]).eval(), np.linalg.solve(dense, rhs[:, 0])
        )


def test_likelihood_with_a_low_rank_covariance_matches_mvnormal():
    r, d, F = _low_rank_instance(10, 3, seed=9)
    models = []
    for structured in (True, False):
        with pm.Model() as model:
            s = pm.HalfNormal("s")
            a = pm.HalfNormal("a")
            cov = (
                low_rank_covariance(s**2 + d, a * F)
                if structured
                else pt.diag(s**2 + d) + a**2 * F @ F.T
            )
            (GaussianLikelihood if structured else pm.MvNormal)(
                "y", mu=pt.zeros(10), cov=cov, observed=r
            )
        models.append(model)
    woodbury = models[0].compile_logp(vars=models[0].observed_RVs)
    assert "WoodburyLogDensity" in str(woodbury.f.maker.fgraph.toposort())  # k × k only
    point = {"s_log__": np.array(-0.3), "a_log__": np.array(0.4)}
    np.testing.assert_allclose(
        models[0].compile_logp()(point), models[1].compile_logp()(point), rtol=1e-12
    )
    np.testing.assert_allclose(
        models[0].compile_dlogp()(point), models[1].compile_dlogp()(point), rtol=1e-9
    )
