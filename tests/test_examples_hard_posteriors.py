"""The hard-posterior example problems: Jacobians, reproducible data, priors, hardness.

The hardness of each problem is checked on a Laplace approximation with the noise sd
known (numpy and scipy only, no sampling): the Gauss–Newton Hessian ``JᵀJ / σ²`` of the
likelihood at the least-squares fit plus the curvature of the priors.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from kohpymc.examples import hard_posteriors as hp

NAMES = ["linear", "arrhenius", "collinear", "multiplicative"]


@pytest.fixture(scope="module")
def problems():
    return hp.all_problems()


def _central_differences(physics, inputs, params, rel=1e-6):
    columns = []
    for name, value in params.items():
        step = rel * max(abs(value), 1e-12)
        up, down = dict(params), dict(params)
        up[name], down[name] = value + step, value - step
        diff = physics.evaluate(inputs, up) - physics.evaluate(inputs, down)
        columns.append(diff / (2.0 * step))
    return np.column_stack(columns)


def _prior_curvature(prior, value):
    """``d² (-log p) / dθ²`` in natural units."""
    if prior.kind == "normal":
        return 1.0 / prior.args["sigma"] ** 2
    if prior.kind == "uniform":
        return 0.0
    if prior.kind == "lognormal":
        mu, s = prior.args["mu"], prior.args["sigma"]
        return (1.0 / s**2 - 1.0 - (math.log(value) - mu) / s**2) / value**2
    raise AssertionError(prior.kind)  # pragma: no cover


def _least_squares_fit(problem):
    physics, data = problem.physics, problem.data
    names = physics.parameter_names
    start = np.array([problem.truth[k] for k in names])
    fit = least_squares(
        lambda q: physics.evaluate(data.inputs, q) - data.y,
        start,
        jac=lambda q: physics.jacobian_matrix(data.inputs, q),
        x_scale="jac",
        xtol=1e-14,
        ftol=1e-14,
        gtol=1e-14,
    )
    assert fit.success
    return dict(zip(names, fit.x, strict=True))


def _laplace_covariance(problem, at):
    physics, data = problem.physics, problem.data
    J = physics.jacobian_matrix(data.inputs, at)
    H = J.T @ J / problem.true_noise_sd**2
    H += np.diag([_prior_curvature(p, at[k]) for k, p in physics.parameters.items()])
    assert np.all(np.linalg.eigvalsh(H) > 0)
    return np.linalg.inv(H)


def _correlation(cov):
    sd = np.sqrt(np.diag(cov))
    return float(cov[0, 1] / (sd[0] * sd[1]))


# ----------------------------------------------------------------------------- structure
def test_all_problems_by_name(problems):
    assert list(problems) == NAMES
    for name, problem in problems.items():
        assert problem.name == name
        assert isinstance(problem, hp.Problem)
        assert problem.description and problem.informed
        assert problem.physics.jacobian is not None
        assert problem.physics.backend == "numpy"
        assert set(problem.truth) == set(problem.physics.parameter_names)
        assert problem.data.input_names == problem.physics.inputs
        assert 20 <= problem.data.n <= 40
        assert problem.data.noise_sd is None
    assert problems["multiplicative"].informed == "k*c"


def test_problem_is_frozen(problems):
    with pytest.raises(AttributeError):
        problems["linear"].name = "other"


@pytest.mark.parametrize("name", NAMES)
def test_known_noise_is_recorded_and_used(name):
    make = getattr(hp, name)
    known = make(seed=3, noise_sd=0.02)
    unknown = make(seed=3)
    assert known.data.noise_sd == 0.02
    assert known.true_noise_sd == 0.02
    clean = known.physics.evaluate(known.data.inputs, known.truth)
    # the same standard-normal draws, scaled by the noise sd
    np.testing.assert_allclose(
        (known.data.y - clean) / 0.02, (unknown.data.y - clean) / unknown.true_noise_sd
    )
    with pytest.raises(ValueError, match="noise_sd"):
        make(noise_sd=0.0)


# ------------------------------------------------------------------------------ Jacobian
@pytest.mark.parametrize("name", NAMES)
def test_analytic_jacobian_matches_central_differences(problems, name):
    problem = problems[name]
    inputs = problem.data.inputs
    analytic = problem.physics.jacobian_matrix(inputs, problem.truth)
    numeric = _central_differences(problem.physics, inputs, problem.truth)
    assert analytic.shape == (problem.data.n, len(problem.truth))
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=0.0)


# ---------------------------------------------------------------------------------- data
@pytest.mark.parametrize("name", NAMES)
def test_data_reproducible_for_a_seed_and_different_for_another(name):
    make = getattr(hp, name)
    first, again, other = make(seed=0), make(seed=0), make(seed=1)
    np.testing.assert_array_equal(first.data.y, again.data.y)
    for key in first.data.inputs:
        np.testing.assert_array_equal(first.data.inputs[key], other.data.inputs[key])
    assert not np.allclose(first.data.y, other.data.y)


@pytest.mark.parametrize("name", NAMES)
def test_data_scatter_about_the_truth_with_the_noise_sd(name):
    problem = getattr(hp, name)(seed=0)
    clean = problem.physics.evaluate(problem.data.inputs, problem.truth)
    rms = float(np.sqrt(np.mean((problem.data.y - clean) ** 2)))
    assert 0.6 * problem.true_noise_sd < rms < 1.4 * problem.true_noise_sd


@pytest.mark.parametrize("name", NAMES)
def test_truth_inside_the_prior_support(problems, name):
    problem = problems[name]
    for key, prior in problem.physics.parameters.items():
        assert prior.in_support(problem.truth[key])
        if prior.kind == "normal":  # not far in a tail either
            assert abs(problem.truth[key] - prior.args["mu"]) < 2 * prior.args["sigma"]
        if prior.kind == "lognormal":
            z = (math.log(problem.truth[key]) - prior.args["mu"]) / prior.args["sigma"]
            assert abs(z) < 2


# ------------------------------------------------------------------------------ hardness
def test_linear_is_easy(problems):
    problem = problems["linear"]
    cov = _laplace_covariance(problem, _least_squares_fit(problem))
    sd = math.sqrt(cov[0, 0])
    assert 0.01 < sd < 0.1


def test_arrhenius_compensation_and_scales(problems):
    problem = problems["arrhenius"]
    fit = _least_squares_fit(problem)
    cov = _laplace_covariance(problem, fit)
    rho = _correlation(cov)
    assert rho > 0.99  # larger A, larger Ea
    sd_A, sd_Ea = np.sqrt(np.diag(cov))
    assert sd_A / sd_Ea > 1e8  # badly scaled in natural units
    # the fit recovers the truth within a few posterior sd
    assert abs(fit["Ea"] - problem.truth["Ea"]) < 4 * sd_Ea
    assert abs(fit["A"] - problem.truth["A"]) < 4 * sd_A


def test_collinear_correlation_with_both_parameters_identified(problems):
    problem = problems["collinear"]
    fit = _least_squares_fit(problem)
    cov = _laplace_covariance(problem, fit)
    assert abs(_correlation(cov)) > 0.99
    # the data, not only the priors, narrow both parameters
    for i, prior in enumerate(problem.physics.parameters.values()):
        assert math.sqrt(cov[i, i]) < 0.5 * prior.sd()
    # and the likelihood alone has a unique optimum (full-rank Jacobian)
    J = problem.physics.jacobian_matrix(problem.data.inputs, fit)
    assert np.linalg.matrix_rank(J) == 2


def test_multiplicative_informs_only_the_product(problems):
    problem = problems["multiplicative"]
    physics, data, sigma = problem.physics, problem.data, problem.true_noise_sd
    names = physics.parameter_names
    mu = np.array([physics.parameters[k].args["mu"] for k in names])
    s = np.array([physics.parameters[k].args["sigma"] for k in names])
    # The least-squares fit is a whole curve k c = const; take the point of it the priors
    # prefer (the posterior mode) in (ln k, ln c), where the LogNormal priors are Normal.
    fit = least_squares(
        lambda u: np.concatenate(
            [(physics.evaluate(data.inputs, np.exp(u)) - data.y) / sigma, (u - mu) / s]
        ),
        np.log([problem.truth[k] for k in names]),
        xtol=1e-14,
        ftol=1e-14,
        gtol=1e-14,
    )
    assert fit.success
    theta = np.exp(fit.x)
    J_log = physics.jacobian_matrix(data.inputs, theta) * theta  # ∂y/∂ln θ
    cov_log = np.linalg.inv(J_log.T @ J_log / sigma**2 + np.diag(1.0 / s**2))
    sd_log_k = math.sqrt(cov_log[0, 0])
    sd_log_kc = math.sqrt(cov_log.sum())
    assert sd_log_kc < 0.05 * sd_log_k
    assert abs(math.log(theta.prod()) - math.log(10.0)) < 4 * sd_log_kc
    # in natural units the Gauss-Newton Hessian of the likelihood has rank one
    J = physics.jacobian_matrix(data.inputs, dict(zip(names, theta, strict=True)))
    assert np.linalg.matrix_rank(J) == 1
