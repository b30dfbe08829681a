"""Whitened sampling coordinates: exact maps, and draws mapped back against dense references."""

import functools
import json
import warnings

import arviz as az
import numpy as np
import pymc as pm
import pytensor.tensor as pt
import pytest

from kohpymc.reparameterization import (
    Coordinates,
    Reparameterization,
    VarianceShare,
    _bound_ridge_plan,
    _local_hessian,
    _whitened,
    box_ridge_plan,
    find_mode,
    plan,
)
from kohpymc.sampling import sample_posterior, variance_shares
from kohpymc.value_space import value_space

SEED = 20261123


def _finite_difference_gradient(f, x, h=1e-6):
    grad = np.empty_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        grad[i] = (f(x + e) - f(x - e)) / (2 * h)
    return grad


def _finite_difference_jacobian(f, x, h=1e-6):
    """Central differences of a vector function: column ``j`` is ``∂f/∂x_j``."""
    return np.column_stack([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(x.size)])


def _check_plan_exact(space, reparam, z, *, rtol, atol, inverse_atol):
    """At ``z`` the plan's density has the gradient central differences give, and z → v → z
    round trips to ``inverse_atol``; returns the log density."""
    logp, grad = reparam.logp_dlogp(space, z)
    fd = _finite_difference_gradient(lambda u: reparam.logp_dlogp(space, u)[0], z)
    np.testing.assert_allclose(grad, fd, rtol=rtol, atol=atol)
    np.testing.assert_allclose(reparam.from_value(reparam.to_value(z)), z, atol=inverse_atol)
    return logp


def _check_elementwise_map(coords, w, *, h, rtol, atol=0.0):
    """Inverse (1e-10), dv/dw and d log|dv/dw|/dw of elementwise coordinates at ``w``
    against central differences of step ``h``; returns ``v``, ``dv`` and ``log|dv/dw|``."""
    v, dv, dlogjac, logjac = coords.to_value(w)
    np.testing.assert_allclose(coords.from_value(v), w, rtol=1e-10)
    for i, step in enumerate(h * np.eye(w.size)):
        fd = (coords.to_value(w + step)[0][i] - coords.to_value(w - step)[0][i]) / (2 * h)
        np.testing.assert_allclose(dv[i], fd, rtol=rtol)
    fd_logjac = _finite_difference_gradient(lambda u: coords.to_value(u)[3], w, h=h)
    np.testing.assert_allclose(dlogjac, fd_logjac, rtol=rtol, atol=atol)
    return v, dv, logjac


def test_log_coordinates_map_and_jacobian_against_finite_differences():
    """w -> v for Uniform(a, b), a > 0, on the log scale: inverse, dv/dw and d log|dv/dw|/dw."""
    lower, upper = np.array([0.01, 0.8]), np.array([1.0, 1.4])
    coords = Coordinates(np.array([True, True]), lower, upper)
    w = np.array([-1.3, 0.7])
    v, dv, logjac = _check_elementwise_map(coords, w, h=1e-6, rtol=1e-6)
    # x = a (b/a)^p with p = expit(w): the value-space point is logit((x - a)/(b - a))
    p = 1 / (1 + np.exp(-w))
    x = lower * (upper / lower) ** p
    np.testing.assert_allclose(v, np.log((x - lower) / (upper - x)), rtol=1e-12)
    assert logjac == pytest.approx(np.sum(np.log(dv)))


def test_log_coordinates_on_a_bound_give_no_density_and_no_numpy_warning():
    """w = ±40 rounds expit(w) to 0 or 1: x on the bound, dv/dw = 0, log|dv/dw| = -inf.

    A planner probe at ±1.5 sd of LogUniform(1e-2, 1e8) (an unseen creep study's simulation
    check) got there, and numpy's divide/log warnings reached the user.
    """
    coords = Coordinates(np.array([True]), np.array([1e-2]), np.array([1e8]))
    for w in (-800.0, 800.0):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            _, _, _, logjac = coords.to_value(np.array([w]))
        assert not np.isfinite(logjac)  # the callers' sign for "no density here"


def _bounded_model(phi_true=1.1):
    """Fowler–Nordheim-like: the data fix sqrt(m)·phi^1.5 to 1e-3 and ln(m·phi) to 0.05."""
    rng = np.random.default_rng(SEED)
    x = np.linspace(1.0, 2.0, 15)
    m_true = 0.1
    exponent = np.sqrt(m_true) * phi_true**1.5 * x + rng.normal(0, 1e-3, x.size)
    prefactor = np.log(m_true * phi_true) + rng.normal(0, 0.05)
    with pm.Model() as model:
        m = pm.Uniform("m", 0.01, 1.0)
        phi = pm.Uniform("phi", 0.8, 1.4)
        pm.Normal("exponent", pm.math.sqrt(m) * phi**1.5 * x, 1e-3, observed=exponent)
        pm.Normal("prefactor", pm.math.log(m * phi), 0.05, observed=prefactor)
    return model


def test_whitened_density_gradient_and_round_trip():
    """The density in z has the gradient finite differences give, and z <-> v round trips."""
    space = value_space(_bounded_model())
    reparam = plan(space, seed=SEED)
    z = np.array([0.3, -0.8])
    _check_plan_exact(space, reparam, z, rtol=1e-5, atol=1e-6, inverse_atol=1e-8)


def test_multiplicative_ridge_is_sampled_on_the_log_scale():
    """A ridge sqrt(m)·phi^1.5 = const, straight in (ln m, ln phi) and far inside the prior
    bounds: the plan samples both on the log scale, where the posterior is close to Gaussian
    (log-density drops within 0.05 of a Gaussian's at ±1.5 sd), and says why."""
    reparam = plan(value_space(_bounded_model()), seed=SEED)
    assert reparam.kind == "log-affine", reparam.reason
    assert reparam.max_correlation > 0.99
    assert reparam.gaussian_score < 0.05
    assert "log scale" in reparam.reason


def test_ridge_against_a_bound_is_measured_from_its_regression():
    """Data from phi = 1.6, beyond the bound 1.4: phi piles against it and m follows the
    ridge, which bends exponentially in phi's interval coordinate.  The bound-ridge map
    straightens it (log-density drops at ±1.5 sd within 1 of a Gaussian's on average —
    what is left is the Gumbel-like shape of phi's own axis — from 50 in the whitened
    interval coordinates alone), exactly: gradient and round trip hold."""
    space = value_space(_bounded_model(phi_true=1.6))
    reparam = plan(space, seed=SEED)
    assert "bound-ridge-" in reparam.kind, reparam.reason
    assert "phi" in reparam.reason and "prior bound" in reparam.reason
    ridge = reparam.coordinates.ridge
    assert ridge.bounded.tolist() == [1]
    plain = reparam.coordinates.with_ridge(None)
    laplace = _whitened(space, plain, reparam.mode.value, reparam.mode)
    assert laplace.gaussian_score > 10.0 and reparam.gaussian_score < 1.0
    z = np.array([0.7, -1.3])
    _check_plan_exact(space, reparam, z, rtol=1e-5, atol=1e-6, inverse_atol=1e-8)


def test_bound_ridge_with_variance_shares_is_exact():
    """Noise split between two sds (sampled as total sd and log ratio) next to a slope piled
    against its bound: the composed map's gradient and round trip hold."""
    rng = np.random.default_rng(SEED)
    x = np.linspace(1.0, 3.0, 30)
    y = 2.0 * x + rng.normal(0.0, 0.3, x.size)
    with pm.Model() as model:
        a = pm.HalfNormal("a", 1.0)
        b = pm.HalfNormal("b", 1.0)
        c = pm.Uniform("c", 0.5, 1.5)
        pm.Normal("y", c * x, pm.math.sqrt(a**2 + b**2), observed=y)
    space = value_space(model)
    shares = variance_shares(space, [("a", "b")])
    mode = find_mode(space, seed=SEED)
    laplace = _whitened(space, Coordinates.identity(3).with_shares(shares), mode.value, mode)
    bent = _bound_ridge_plan(space, laplace, mode)
    assert bent.kind == "variance-share-bound-ridge-affine"
    assert bent.coordinates.ridge.bounded.tolist() == [2]
    z = np.array([0.3, -0.7, 0.9])
    _check_plan_exact(space, bent, z, rtol=1e-5, atol=1e-6, inverse_atol=1e-8)
    np.testing.assert_allclose(bent.value_sd, laplace.value_sd, rtol=1e-3)


def _piled_moments():
    """Mean and covariance of (m, phi) under _bounded_model(1.6), by dense quadrature in
    (phi, r = sqrt(m)·phi^1.5), where the ridge is an axis (|dm/dr| = 2r/phi³)."""
    rng = np.random.default_rng(SEED)
    x = np.linspace(1.0, 2.0, 15)
    r_true = np.sqrt(0.1) * 1.6**1.5
    exponent = r_true * x + rng.normal(0, 1e-3, x.size)
    prefactor = np.log(0.1 * 1.6) + rng.normal(0, 0.05)
    r_hat = float(exponent @ x / (x @ x))
    sd_r = 1e-3 / np.sqrt(x @ x)
    phi, r = np.meshgrid(
        np.linspace(1.1, 1.4, 3001), np.linspace(r_hat - 10 * sd_r, r_hat + 10 * sd_r, 601)
    )
    m = r**2 / phi**3
    logp = (
        -0.5 * np.sum((exponent[:, None, None] - r * x[:, None, None]) ** 2, axis=0) / 1e-6
        - 0.5 * ((prefactor - np.log(m * phi)) / 0.05) ** 2
        + np.log(2 * r / phi**3)
    )
    p = np.exp(logp - logp.max())
    p /= p.sum()
    assert p[:, :300].sum() < 1e-6  # no mass near phi = 1.1: the grid holds the posterior
    stacked = np.stack([m.ravel(), phi.ravel()])
    mean = stacked @ p.ravel()
    centred = stacked - mean[:, None]
    return mean, (centred * p.ravel()) @ centred.T


def _assert_moments(idata, names, mean, cov, excess_kurtosis=(0.0, 0.0)):
    """The draws' mean, sd and correlation of the two scalars ``names`` match a reference
    ``mean`` and ``cov`` within 4 Monte Carlo errors (Fisher z for the correlation), with an
    ESS above 400.  The sd's relative Monte Carlo error is √((κ + 2)/(4 ESS)) for a
    reference excess kurtosis κ (√(1/(2 ESS)) for a Gaussian, the default)."""
    sd = np.sqrt(np.diag(cov))
    draws = np.column_stack([idata.posterior[k].values.ravel() for k in names])
    ess = float(az.ess(idata, var_names=list(names)).to_array().min())
    assert ess > 400
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 4 * sd / np.sqrt(ess))
    sd_error = np.sqrt((np.asarray(excess_kurtosis) + 2.0) / (4.0 * ess))
    assert np.all(np.abs(draws.std(axis=0, ddof=1) / sd - 1) < 4 * sd_error)
    rho = cov[0, 1] / (sd[0] * sd[1])
    r = np.corrcoef(draws.T)[0, 1]
    assert abs(np.arctanh(r) - np.arctanh(rho)) < 4 / np.sqrt(ess)


def test_draws_against_a_bound_match_a_dense_reference():
    """Sampled in bound-ridge coordinates, the draws' mean and covariance of (m, phi) match
    dense quadrature within 4 Monte Carlo errors (Fisher z for the correlation).

    About 1 % of the transitions diverge, in the double-exponential tail of phi's interval
    coordinate away from the bound (as many as without the map, which needs 5× the
    leapfrog steps for a tenth of the effective sample size: docs/paper-reproduction.md).
    """
    model = _bounded_model(phi_true=1.6)
    with pytest.warns(UserWarning, match="upper prior bound 1.4"):
        idata, report = sample_posterior(model, draws=1000, tune=1000, chains=2, random_seed=SEED)
    assert "bound-ridge-" in report.reparameterization["kind"], report
    assert int(idata.sample_stats.diverging.sum()) < 40
    _assert_moments(idata, ("m", "phi"), *_piled_moments())


_K_BOX, _C_BOX = (1e-8, 1e-6), (1e8, 1e10)


def _product_data():
    """``y = k c x`` with noise sd 0.5: only k·c (= 30) is informed."""
    rng = np.random.default_rng(SEED)
    x = np.linspace(0.05, 1.0, 20)
    return x, 30.0 * x + rng.normal(0.0, 0.5, x.size)


def _product_in_a_box():
    """k ~ U(1e-8, 1e-6), c ~ U(1e8, 1e10) in natural units: the ridge k·c = 30 runs from
    k's lower bound (c = 3e9) to c's lower bound (k = 3e-7), flat in (ln k, ln c)."""
    x, y = _product_data()
    with pm.Model() as model:
        k = pm.Uniform("k", *_K_BOX)
        c = pm.Uniform("c", *_C_BOX)
        pm.Normal("y", k * c * x, 0.5, observed=y)
    return model


def _product_reference():
    """Mean and sd of ln k by quadrature over (ln k, ln c)."""
    x, y = _product_data()
    lk = np.linspace(*np.log(_K_BOX), 1500)
    lc = np.linspace(*np.log(_C_BOX), 1500)
    LK, LC = np.meshgrid(lk, lc, indexing="ij")
    kc = np.exp(LK + LC)
    ss = y @ y - 2 * kc * (x @ y) + kc**2 * (x @ x)
    logp = -ss / (2 * 0.25) + LK + LC  # uniform priors: density in ln k, ln c gains k·c
    w = np.exp(logp - logp.max()).sum(axis=1)
    w /= w.sum()
    mean = float(w @ lk)
    return mean, float(np.sqrt(w @ (lk - mean) ** 2))


def test_flat_ridge_in_a_prior_box_is_sampled_along_its_segment():
    """Only k·c informed, k and c in prior boxes: every Laplace map fits badly (Gaussian
    score > 10: in PyMC's coordinates the ridge is an L running off to infinity), the plan
    samples across the ridge whitened and along it between the bounds, exactly (gradient
    and round trip), and the flat ridge is a logistic in t (score < 1)."""
    space = value_space(_product_in_a_box())
    reparam = plan(space, seed=SEED)
    assert reparam.kind == "box-ridge-log", reparam.reason
    assert "k, c" in reparam.reason and "prior bounds" in reparam.reason
    assert reparam.gaussian_score < 1.0
    box = box_ridge_plan(space, reparam.mode)
    laplace = _whitened(space, Coordinates.identity(2), reparam.mode.value, reparam.mode)
    assert laplace is None or laplace.gaussian_score > 10.0
    for z in (np.array([0.4, -1.1]), np.array([-0.7, 2.5])):
        _check_plan_exact(space, box, z, rtol=1e-5, atol=1e-6, inverse_atol=1e-7)
        value = box.to_value(z)
        assert np.all(np.isfinite(value))


def test_flat_ridge_from_corner_to_corner_goes_along_its_segment_and_samples_cleanly():
    """k·c = 100 with k, c log-uniform over 1e-8..1e-6 and 1e8..1e10: the ridge runs from
    corner to corner, a Laplace map fits near the mode (score ~0.2, below the segment's)
    and was chosen, with 11-18 divergences and ESS 95-264 in 4 × 1000 draws over three
    seeds.  The segment is chosen whenever it fits (score < 1), and samples cleanly."""
    from kohpymc.priors import LogUniform

    rng = np.random.default_rng(SEED)
    x = np.linspace(0.0, 1.0, 20)
    with pm.Model() as model:
        k = LogUniform(*_K_BOX).create("k")
        c = LogUniform(*_C_BOX).create("c")
        pm.Normal("y", k * c * x, 2.0, observed=100.0 * x + rng.normal(0.0, 2.0, x.size))
    space = value_space(model)
    reparam = plan(space, seed=SEED)
    assert reparam.kind == "box-ridge-log", reparam.reason
    idata, report = sample_posterior(model, draws=500, tune=500, chains=2, random_seed=SEED)
    assert report.reparameterization["kind"] == "box-ridge-log"
    assert int(idata.sample_stats.diverging.sum()) == 0
    assert float(az.rhat(idata).to_array().max()) <= 1.01
    # log-uniform priors and a flat ridge: ln k is uniform on its whole box
    lk = np.log(idata.posterior["k"].values.ravel())
    half_width = 0.5 * np.log(_K_BOX[1] / _K_BOX[0])
    assert abs(lk.mean() - np.log(np.sqrt(_K_BOX[0] * _K_BOX[1]))) < 0.15 * half_width
    assert abs(lk.std() - 2 * half_width / np.sqrt(12)) < 0.1 * lk.std()


def _assert_box_ridge_draws(idata, report, reference):
    """Sampled along the box ridge: no divergences, r̂ ≤ 1.01, ESS > 300, and ln k's mean
    and sd within 4 Monte Carlo errors of the quadrature ``reference`` (mean, sd)."""
    assert report.reparameterization["kind"] == "box-ridge-log", report
    assert int(idata.sample_stats.diverging.sum()) == 0
    assert float(az.rhat(idata).to_array().max()) <= 1.01
    ess = float(az.ess(idata, var_names=["k", "c"]).to_array().min())
    assert ess > 300
    lk = np.log(idata.posterior["k"].values.ravel())
    mean, sd = reference
    assert abs(lk.mean() - mean) < 4 * sd / np.sqrt(ess)
    assert abs(lk.std(ddof=1) / sd - 1) < 4 / np.sqrt(2 * ess)


def test_draws_along_a_flat_ridge_in_a_box_match_a_dense_reference():
    """r̂ 1.6, 196 divergences and bulk ESS 7 in 4 × 1000 draws before (the uniform-box
    product, log-uniform priors alike); now 0 divergences, and ln k's mean and sd match
    quadrature within 4 Monte Carlo errors."""
    idata, report = sample_posterior(
        _product_in_a_box(), draws=500, tune=500, chains=2, random_seed=SEED
    )
    _assert_box_ridge_draws(idata, report, _product_reference())


def _product_with_shared_noise():
    """``y = k c x`` (k, c in their boxes) with the noise split between two sds, ``a`` and
    ``b`` (HalfNormal(1) each), of which only ``a² + b²`` enters: variance shares and a
    flat ridge in the log of k and c together (the pipe case's M2/M3: a·ρ^0.7 and K·ρ)."""
    x, y = _product_data()
    with pm.Model() as model:
        k = pm.Uniform("k", *_K_BOX)
        c = pm.Uniform("c", *_C_BOX)
        a = pm.HalfNormal("a", 1.0)
        b = pm.HalfNormal("b", 1.0)
        pm.Normal("y", k * c * x, pm.math.sqrt(a**2 + b**2), observed=y)
    return model


def _shared_noise_reference():
    """Mean and sd of ln k under :func:`_product_with_shared_noise` by quadrature.

    ``s² = a² + b²`` of two HalfNormal(1) sds is χ²₂, so ``s`` has the Rayleigh density
    ``s e^{−s²/2}``; with ``m = ln(k c)`` the density in ``(ln k, m)`` is ``e^m L(m)``
    (uniform priors in k and c) on the box, ``L(m) = ∫ Rayleigh(s) N(y | e^m x, s) ds``.
    """
    x, y = _product_data()
    s = np.linspace(0.05, 2.0, 800)
    m = np.linspace(np.log(28.0), np.log(32.0), 1601)
    ss = y @ y - 2 * np.exp(m)[:, None] * (x @ y) + np.exp(2 * m)[:, None] * (x @ x)
    loglik = -x.size * np.log(s) - ss / (2 * s**2) + np.log(s) - s**2 / 2
    log_m = np.log(np.exp(loglik - loglik.max()).sum(axis=1)) + m
    weight_m = np.exp(log_m - log_m.max())
    lk = np.linspace(*np.log(_K_BOX), 3000)
    inside = (m[None, :] - lk[:, None] > np.log(_C_BOX[0])) & (
        m[None, :] - lk[:, None] < np.log(_C_BOX[1])
    )
    w = inside @ weight_m
    w /= w.sum()
    mean = float(w @ lk)
    return mean, float(np.sqrt(w @ (lk - mean) ** 2))


def test_flat_ridge_in_a_box_with_variance_shares_goes_along_its_segment():
    """With variance shares the box-ridge map was never tried (only a Laplace map, bent or
    not, whose trouble lies beyond the ±1.5 sd the score looks at: pipe M2/M3, r̂ 1.011-1.031,
    ESS 132-223); now the shares act on the other coordinates of the segment's map, which
    is exact (gradient against central differences, round trip) and chosen."""
    space = value_space(_product_with_shared_noise())
    shares = variance_shares(space, [("a", "b")])
    reparam = plan(space, seed=SEED, shares=shares)
    assert reparam.kind == "box-ridge-log", reparam.reason
    assert reparam.coordinates.shares == shares
    for z in (np.array([0.4, -1.1, 0.8, 0.3]), np.array([-0.7, 1.5, -2.0, 2.5])):
        _check_plan_exact(space, reparam, z, rtol=1e-5, atol=1e-6, inverse_atol=1e-7)


def test_draws_along_a_flat_ridge_with_variance_shares_match_a_dense_reference():
    """Sampled with the variance shares on (a, b): no divergences, and ln k's mean and sd
    match quadrature within 4 Monte Carlo errors."""
    idata, report = sample_posterior(
        _product_with_shared_noise(), draws=500, tune=500, chains=2, random_seed=SEED,
        variance_pairs=[("a", "b")],
    )  # fmt: skip
    _assert_box_ridge_draws(idata, report, _shared_noise_reference())


def test_mode_of_a_conjugate_normal_model():
    """Posterior mode of a normal mean with a normal prior: (Σy/σ²)/(n/σ² + 1/τ²)."""
    y = np.array([0.4, 1.1, 2.3, 1.7])
    with pm.Model() as model:
        mu = pm.Normal("mu", 0.0, 2.0)
        pm.Normal("y", mu, 0.5, observed=y)
    mode = find_mode(value_space(model), seed=SEED)
    expected = (y.sum() / 0.25) / (y.size / 0.25 + 1 / 4.0)
    assert mode.value[0] == pytest.approx(expected, rel=1e-6)


def _gaussian_model(mean, sd, rho):
    cov = np.array([[sd[0] ** 2, rho * sd[0] * sd[1]], [rho * sd[0] * sd[1], sd[1] ** 2]])
    with pm.Model(coords={"param": ["small", "large"]}) as model:
        pm.MvNormal("theta", mu=mean, cov=cov, dims="param")
    return model, cov


def _t_and_data_density(x):
    """Student-t (ν = 4) coordinates at modes 0 and 1e3 with scales 1e-5..1e5, and a
    Gaussian coordinate at 0 whose gradient sums 200 large data terms (rounding noise)."""
    loc = np.array([0.0, 0.0, 0.0, 1e3, 1e3, 1e3])
    scale = np.array([1e-5, 1.0, 1e5, 1e-5, 1.0, 1e5])
    z = (x[:6] - loc) / scale
    logp = float(np.sum(-2.5 * np.log1p(z**2 / 4)))
    grad_t = -2.5 * (2 * z / 4) / (1 + z**2 / 4) / scale
    data = np.repeat([-1e6, 1e6], 100)
    logp += float(np.sum(-0.5 * (data - x[6]) ** 2))
    grad_data = np.sum(data - x[6])
    curvature = np.append(2.5 * 0.5 / scale**2, data.size)
    return logp, np.append(grad_t, grad_data), curvature


def test_hessian_at_modes_near_zero_and_far_from_it_matches_the_analytic_one():
    # a step 1e-5·max(|x|, 1e-3) is 1e3 sds at x = 1e3 with sd 1e-5 (relative error ~1)
    # and 1e-8 at x = 0, where the summed data gradient leaves 0.2 % rounding noise
    x = np.array([0.0, 0.0, 0.0, 1e3, 1e3, 1e3, 0.0])
    curvature = _t_and_data_density(x)[2]
    hess = _local_hessian(lambda w: _t_and_data_density(w)[:2], x)
    # x + step rounds at 1e-16·|x|: 1e-5 of a 1e-8 step at x = 1e3
    np.testing.assert_allclose(np.diag(hess), curvature, rtol=1e-4)
    scaled = hess / np.sqrt(np.outer(curvature, curvature))
    np.testing.assert_allclose(scaled - np.diag(np.diag(scaled)), 0.0, atol=1e-6)


def test_draws_mapped_back_match_a_dense_gaussian_reference():
    """Correlation 0.9999, scales 1e-5 and 1e5: mean and covariance of the draws against the
    exact ones, within 4 Monte Carlo standard errors (Fisher z for the correlation)."""
    mean = np.array([3e-5, -2e5])
    sd = np.array([1e-5, 1e5])
    rho = 0.9999
    model, cov = _gaussian_model(mean, sd, rho)
    idata, report = sample_posterior(model, draws=1000, tune=500, chains=2, random_seed=SEED)
    assert report.sampler == "nutpie"
    assert report.reparameterization["kind"] == "affine"
    assert int(idata.sample_stats.diverging.sum()) == 0
    draws = idata.posterior["theta"].values.reshape(-1, 2)
    ess = float(az.ess(idata, var_names=["theta"])["theta"].min())
    assert ess > 400
    se_mean = sd / np.sqrt(ess)
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 4 * se_mean)
    sd_hat = draws.std(axis=0, ddof=1)
    assert np.all(np.abs(sd_hat / sd - 1) < 4 / np.sqrt(2 * ess))
    r = np.corrcoef(draws.T)[0, 1]
    assert abs(np.arctanh(r) - np.arctanh(rho)) < 4 / np.sqrt(ess)


def test_plan_without_a_positive_hessian_falls_back_with_the_reason():
    """A flat direction (improper, unidentified sum): plan 'none' and says why."""
    with pm.Model() as model:
        a = pm.Flat("a")
        b = pm.Flat("b")
        pm.Normal("y", a + b, 1.0, observed=[0.3, 0.5])
    reparam = plan(value_space(model), seed=SEED)
    assert reparam.kind == "none"
    assert "not positive definite" in reparam.reason
    assert isinstance(reparam, Reparameterization)


def test_separated_modes_are_reported():
    """y = a² + noise with a symmetric prior: modes at ±a, many sds apart -> a warning."""
    with pm.Model() as model:
        a = pm.Normal("a", 0.0, 3.0)
        pm.Normal("y", a**2, 0.05, observed=[4.0, 4.02, 3.98])
    reparam = plan(value_space(model), seed=SEED, n_design=8)
    assert any("separated modes" in w for w in reparam.warnings), reparam.warnings


def test_separated_modes_counted_once_each_and_named_in_the_parameters_units():
    """Two modes (a = ±2 of y = a² + noise), each found from several starts: "2 modes", both named.

    The modes are ±sqrt(mean(y)) = ±2.0 (computed here, not by the code); the warning
    gives a at each to 3 significant digits, and the other parameter (b, the same at both).
    """
    y = np.array([4.0, 4.02, 3.98])
    with pm.Model() as model:
        a = pm.Normal("a", 0.0, 3.0)
        b = pm.Normal("b", 0.0, 1.0, shape=(1,))  # a length-1 vector is named as a scalar
        pm.Normal("y", a**2 + b[0] * np.array([-1.0, 0.0, 1.0]), 0.05, observed=y)
    reparam = plan(value_space(model), seed=SEED, n_design=16)
    (text,) = [w for w in reparam.warnings if "separated modes" in w]
    assert "has 2 separated modes" in text
    root = np.sqrt(y.mean())
    assert f"a={root:.3g}" in text and f"a={-root:.3g}" in text, text
    assert text.count("b=") == 2


def test_variance_share_map_is_volume_preserving_with_the_right_gradient():
    """(t, u) -> (ln a, ln b): round trip, a² + b² = e^{2t}, b/a = e^u, Jacobian det 1, and
    the pulled-back gradient against finite differences of a test function."""
    shares = VarianceShare(((0, 2, 1.0),))
    w = np.array([0.4, 7.0, -1.3])
    v = shares.forward(w)
    np.testing.assert_allclose(shares.inverse(v), w, rtol=1e-12)
    assert np.exp(2 * v[0]) + np.exp(2 * v[2]) == pytest.approx(np.exp(2 * w[0]))
    assert v[2] - v[0] == pytest.approx(w[2])
    assert v[1] == w[1]
    jac = np.column_stack(
        [(shares.forward(w + e) - shares.forward(w - e)) / 2e-6 for e in np.eye(3) * 1e-6]
    )
    assert np.linalg.det(jac) == pytest.approx(1.0, rel=1e-8)

    def f(v):
        return np.sin(v[0]) * v[2] ** 2 + v[1] * v[2]

    grad_v = np.array([np.cos(v[0]) * v[2] ** 2, v[2], 2 * v[0 + 2] * np.sin(v[0]) + v[1]])
    fd = _finite_difference_gradient(lambda u: f(shares.forward(u)), w)
    np.testing.assert_allclose(shares.pull_back(w, grad_v), fd, rtol=1e-6, atol=1e-8)


def _sum_of_squares_model():
    """Only a² + b² is informed (noise next to an iid discrepancy), n = 40."""
    y = np.random.default_rng(SEED).normal(0.0, 0.5, 40)
    with pm.Model() as model:
        a = pm.HalfNormal("a", 1.0)
        b = pm.HalfNormal("b", 1.0)
        pm.Normal("y", 0.0, pm.math.sqrt(a**2 + b**2), observed=y)
    return model, y


def _grid_moments(y):
    """Posterior mean and sd of a and b by quadrature on a dense grid."""
    grid = np.linspace(1e-4, 1.5, 1200)
    a, b = np.meshgrid(grid, grid, indexing="ij")
    s2 = a**2 + b**2
    logp = -0.5 * (a**2 + b**2) - 0.5 * y.size * np.log(s2) - 0.5 * np.sum(y**2) / s2
    p = np.exp(logp - logp.max())
    p /= p.sum()
    out = {}
    for name, x in (("a", a), ("b", b)):
        mean = float((p * x).sum())
        out[name] = (mean, float(np.sqrt((p * (x - mean) ** 2).sum())))
    return out


def test_sum_of_squares_pair_is_sampled_in_variance_share_coordinates():
    """The curved ridge a² + b² = const: sampled as (total sd, log ratio) with 0 divergences;
    the means and sds of a and b match dense quadrature within 4 Monte Carlo errors."""
    model, y = _sum_of_squares_model()
    idata, report = sample_posterior(
        model, draws=1000, tune=1000, chains=2, random_seed=SEED, variance_pairs=[("a", "b")]
    )
    assert report.reparameterization["kind"].startswith("variance-share"), report
    assert "sum of squares" in report.reparameterization["reason"]
    assert int(idata.sample_stats.diverging.sum()) == 0
    reference = _grid_moments(y)
    for name, (mean, sd) in reference.items():
        draws = idata.posterior[name].values.ravel()
        ess = float(az.ess(idata, var_names=[name])[name])
        assert ess > 400
        assert abs(draws.mean() - mean) < 4 * sd / np.sqrt(ess), name
        assert abs(draws.std(ddof=1) / sd - 1) < 4 / np.sqrt(2 * ess) + 0.02, name


def test_variance_pairs_naming_a_fixed_parameter_are_ignored():
    """σ_obs known (not a free parameter): no share map, no error."""
    model, _ = _sum_of_squares_model()
    assert variance_shares(value_space(model), [("sigma_obs", "b")]) is None


def test_variance_share_with_a_log_variance_entry():
    """c = 2: the entry is ln σ_b² ; round trip, sum of squares, gradient, det = 2."""
    shares = VarianceShare(((1, 0, 2.0),))
    w = np.array([0.8, -0.2])
    v = shares.forward(w)
    np.testing.assert_allclose(shares.inverse(v), w, rtol=1e-12)
    assert np.exp(2 * v[1]) + np.exp(v[0]) == pytest.approx(np.exp(2 * w[1]))
    jac = np.column_stack(
        [(shares.forward(w + e) - shares.forward(w - e)) / 2e-6 for e in np.eye(2) * 1e-6]
    )
    assert abs(np.linalg.det(jac)) == pytest.approx(2.0, rel=1e-7)
    grad_v = np.array([np.cos(v[0]) * v[1], np.sin(v[0]) + 3 * v[1] ** 2])
    fd = _finite_difference_gradient(lambda u: (lambda x: np.sin(x[0]) * x[1] + x[1] ** 3)(
        shares.forward(u)), w)  # fmt: skip
    np.testing.assert_allclose(shares.pull_back(w, grad_v), fd, rtol=1e-6, atol=1e-8)


def _line_physics(jacobian):
    from kohpymc import CalibrationData, PhysicsModel
    from kohpymc.priors import Normal

    x = np.linspace(0.0, 2.0, 15)
    y = 1.5 * x + np.random.default_rng(SEED).normal(0.0, 0.1, x.size)
    physics = PhysicsModel(
        lambda i, p: p["a"] * i["x"],
        {"a": Normal(1.0, 2.0)},
        inputs=["x"],
        jacobian=jacobian,
    )
    return physics, CalibrationData({"x": x}, y, noise_sd=0.1)


@pytest.mark.parametrize("factor", [1.0, 1.3])
def test_a_wrong_physics_jacobian_is_reported(factor):
    """A Jacobian 30 % off gives a log-density gradient that finite differences contradict:
    the plan warns and names sampler='smc'; the right Jacobian gives no warning."""
    from kohpymc.model import compose_model

    physics, data = _line_physics(lambda i, p: {"a": factor * i["x"]})
    space = value_space(compose_model(physics, data, None).model)
    reparam = plan(space, seed=SEED)
    flagged = [w for w in reparam.warnings if "finite differences" in w]
    assert bool(flagged) == (factor != 1.0), reparam.warnings
    if flagged:
        assert "sampler='smc'" in flagged[0]


def test_round_off_in_the_log_density_is_not_reported_as_a_noisy_gradient():
    """A ripple of ~1e-6 in the log density (an emulator's predictive covariance has ~1e-7)
    is far below what a leapfrog step feels: no warning (a 1e-4 sd finite-difference step
    reports it as a relative error of ~1e-2); a 30 % wrong Jacobian still is (above)."""
    from kohpymc import CalibrationData, PhysicsModel
    from kohpymc.model import compose_model
    from kohpymc.priors import Normal

    x = np.linspace(0.0, 2.0, 15)
    y = 1.5 * x + np.random.default_rng(SEED).normal(0.0, 0.1, x.size)

    def rippled(i, p):  # value off by ~3e-8 relative, on a scale of 1e-8 in a
        return p["a"] * i["x"] * (1.0 + 3e-8 * np.sin(7e8 * p["a"]))

    physics = PhysicsModel(
        rippled, {"a": Normal(1.0, 2.0)}, inputs=["x"], jacobian=lambda i, p: {"a": i["x"]}
    )
    data = CalibrationData({"x": x}, y, noise_sd=0.1)
    space = value_space(compose_model(physics, data, None).model)
    from kohpymc.reparameterization import _gradient_mismatch

    found = plan(space, seed=SEED)
    assert not [w for w in found.warnings if "finite differences" in w], found.warnings
    # whitened at the mode (a's sd 0.022), as the check sees every plan
    white = Reparameterization(
        "affine", found.mean, np.diag(found.value_sd), Coordinates.identity(1), ""
    )
    assert _gradient_mismatch(space, white, SEED) == ()
    assert _gradient_mismatch(space, white, SEED, step=1e-4)  # the old step: reported


def _jittery_solver(inputs, params):
    """a·exp(−b·x) from a solver stopped at a relative tolerance of 1e-5 (jitters with θ)."""
    exact = params["a"] * np.exp(-params["b"] * inputs["x"])
    return exact * (1.0 + 1e-5 * np.sin(1e7 * params["a"] + 3e7 * params["b"] + 17 * inputs["x"]))


def test_a_noisy_gradient_is_named_as_such_not_as_a_flat_direction():
    """Finite differences of a jittering simulator make the Hessian at the mode indefinite.
    The plan said "flat in some direction ... the data do not inform", though a and b are
    well identified (NUTS recovers them); it now names the noisy gradient and sampler='smc'
    (a structural ridge still gives the flat-direction warning: test_calibration)."""
    from kohpymc import CalibrationData, PhysicsModel, Uniform
    from kohpymc.model import compose_model

    x = np.linspace(0.0, 4.0, 25)
    y = 2.0 * np.exp(-0.7 * x) + np.random.default_rng(3).normal(0.0, 0.01, x.size)
    physics = PhysicsModel(
        _jittery_solver, {"a": Uniform(0.1, 10.0), "b": Uniform(0.01, 5.0)}, inputs=["x"]
    )
    space = value_space(compose_model(physics, CalibrationData({"x": x}, y), None).model)
    warnings = plan(space, seed=1).warnings
    assert any("gradient of the log density is noisy" in w for w in warnings), warnings
    assert not any("flat in some direction" in w for w in warnings), warnings
    assert "sampler='smc'" in warnings[0]


def test_soft_box_coordinates_map_and_jacobian_against_finite_differences():
    """ξ -> v for Uniform(a, b) through the soft box: the identity in the parameter's units
    well inside (x = ξ), no wall beyond the bounds, inverse, dv/dξ and d log|dv/dξ|/dξ."""
    from kohpymc.ridge_curve import SoftBoxCoordinates

    lower, upper = np.array([16.1, 0.01]), np.array([25.3, 1.0])
    coords = SoftBoxCoordinates(
        np.zeros(2, bool), lower, upper, soft=np.ones(2, bool), width=np.array([0.1, 0.005])
    )
    for w in (np.array([16.47, 0.963]), np.array([15.9, 1.02]), np.array([16.12, 0.995])):
        v, _, logjac = _check_elementwise_map(coords, w, h=1e-7, rtol=1e-5, atol=1e-6)
        assert np.all(np.isfinite(v)) and np.isfinite(logjac)
    # far from the upper bound, x = ξ + h·log(1 + e^{-(ξ - a)/h}): 3.7 widths inside the
    # lower one x is 0.024 widths off ξ, 100 widths inside it equals ξ
    x = lower + (upper - lower) / (1 + np.exp(-coords.to_value(np.array([16.47, 0.5]))[0]))
    np.testing.assert_allclose(x - [16.47, 0.5], [0.1 * np.log1p(np.exp(-3.7)), 0.0], atol=1e-9)


_X_CURVE = np.linspace(1.0, 2.0, 15)


def _curved_ridge_data():
    """√m·φ^1.5 fixed to 10⁻³ (φ free over its box), and g + φ/2 observed with sd 0.05."""
    rng = np.random.default_rng(SEED)
    exponent = np.sqrt(0.1) * 1.28**1.5 * _X_CURVE + rng.normal(0, 1e-3, _X_CURVE.size)
    return exponent, 0.70 + rng.normal(0, 0.05)


def _curved_ridge_model():
    """A Fowler–Nordheim ridge from φ = 0.8 to 1.4 (m = c/φ³, curved in m's units), and a
    partner g whose conditional mode moves 6 sds along it, onto its lower bound at φ = 1.4."""
    exponent, y2 = _curved_ridge_data()
    with pm.Model() as model:
        m = pm.Uniform("m", 0.01, 1.0)
        phi = pm.Uniform("phi", 0.8, 1.4)
        g = pm.Uniform("g", 0.0, 1.0)
        pm.Normal("exponent", pm.math.sqrt(m) * phi**1.5 * _X_CURVE, 1e-3, observed=exponent)
        pm.Normal("y2", g + 0.5 * phi, 0.05, observed=y2)
    return model


def _curved_ridge_reference():
    """Means and sds of m, φ and g by quadrature over (ln φ, ln(√m φ^1.5), g)."""
    exponent, y2 = _curved_ridge_data()
    u_hat = np.log((exponent @ _X_CURVE) / (_X_CURVE @ _X_CURVE))
    log_phi = np.linspace(np.log(0.8), np.log(1.4), 301)[:, None, None]
    u = np.linspace(u_hat - 0.004, u_hat + 0.004, 161)[None, :, None]
    g = np.linspace(0.0, 1.0, 401)[None, None, :]
    phi, m = np.exp(log_phi), np.exp(2 * u - 3 * log_phi)
    residual = exponent - np.exp(u[..., 0])[..., None] * _X_CURVE
    logp = (
        -(residual**2).sum(-1)[..., None] / 2e-6
        - (y2 - g - 0.5 * phi) ** 2 / (2 * 0.05**2)
        + np.log(m * phi)  # uniform priors on (m, φ): the Jacobian to (ln φ, u)
    )
    weight = np.where((m > 0.01) & (m < 1.0), np.exp(logp - logp.max()), 0.0)
    weight /= weight.sum()
    moments = {}
    for name, value in (("m", m), ("phi", phi), ("g", g)):
        value = np.broadcast_to(value, weight.shape)
        mean = float((weight * value).sum())
        moments[name] = (mean, float(np.sqrt((weight * (value - mean) ** 2).sum())))
    return moments


def test_curved_ridge_between_box_faces_is_followed_exactly():
    """The ridge plan is chosen (every Laplace map scores > 10), and its map is exact: the
    gradient finite differences give, the round trip, finite everywhere (no walls)."""
    space = value_space(_curved_ridge_model())
    reparam = plan(space, seed=SEED)
    assert reparam.kind == "ridge-curve-soft-box", reparam.reason
    assert "led by phi" in reparam.reason and "g in their own units" in reparam.reason
    assert reparam.gaussian_score < 1.0
    laplace = _whitened(space, Coordinates.identity(3), reparam.mode.value, reparam.mode)
    assert laplace is None or laplace.gaussian_score > 10.0
    for z in (np.array([0.4, -1.1, 0.3]), np.array([-2.5, 2.0, -1.7]), np.array([6.0, 3, -3])):
        logp = _check_plan_exact(space, reparam, z, rtol=1e-5, atol=1e-5, inverse_atol=1e-7)
        assert np.isfinite(logp)


def test_draws_along_a_curved_ridge_match_a_dense_reference():
    """Before (bound-ridge Laplace map; 2 × (500 + 500), seed as here): 76 leapfrog steps per
    draw, 8 divergences, ESS 67 and φ's mean 0.94 ± 0.10 against 1.02 ± 0.16.  Along the
    curve: no divergence, and the means and sds of m, φ, g match quadrature within 4 Monte
    Carlo errors."""
    idata, report = sample_posterior(
        _curved_ridge_model(), draws=500, tune=500, chains=2, random_seed=SEED
    )
    assert report.reparameterization["kind"] == "ridge-curve-soft-box", report
    assert int(idata.sample_stats.diverging.sum()) == 0
    assert float(az.rhat(idata).to_array().max()) <= 1.01
    ess = float(az.ess(idata).to_array().min())
    assert ess > 400
    for name, (mean, sd) in _curved_ridge_reference().items():
        draws = idata.posterior[name].values.ravel()
        assert abs(draws.mean() - mean) < 4 * sd / np.sqrt(ess), name
        assert abs(draws.std(ddof=1) / sd - 1) < 4 / np.sqrt(2 * ess), name


def _step_response(inputs, p, xp=pt):
    """A damped spring-mass's displacement after a step force (under-damped branch)."""
    t, force = inputs["t"], inputs["F"]
    k, m, c = p["k"], p["m"], p["c"]
    wn = xp.sqrt(k / m)
    zeta = c / (2.0 * xp.sqrt(k * m))
    wd = wn * xp.sqrt(1.0 - zeta**2)
    ring = xp.exp(-zeta * wn * t) * (xp.cos(wd * t) + zeta * wn / wd * xp.sin(wd * t))
    return force / k * (1.0 - ring)


def test_mode_search_adds_starts_until_a_second_one_reaches_the_best():
    """An oscillator's frequency gives the posterior many local optima; k (N/m), m (kg) and
    c (N·s/m) log-uniform over 4, 3 and 4 decades.  The 1 + 4 starts of the first design
    missed the global mode at 2 of these 4 seeds; the mode found must be the least-squares
    fit started at the truth (its basin) at every seed."""
    from scipy.optimize import least_squares

    from kohpymc import CalibrationData, LogUniform, NoDiscrepancy, PhysicsModel
    from kohpymc.model import compose_model

    truth = {"k": 25.0, "m": 0.04, "c": 0.2}
    t = np.tile(np.linspace(0.0, 0.6, 25), 3)
    force = np.repeat([0.5, 1.0, 2.0], 25)
    rows = {"t": t, "F": force}
    y = _step_response(rows, truth, np) + np.random.default_rng(7).normal(0.0, 5e-4, t.size)
    priors = {"k": LogUniform(0.1, 1e3), "m": LogUniform(1e-3, 1.0), "c": LogUniform(1e-3, 10.0)}
    physics = PhysicsModel(lambda x, p: _step_response(x, p, np), priors, inputs=["t", "F"])
    data = CalibrationData({"t": t, "F": force}, y, noise_sd=5e-4)
    space = value_space(compose_model(physics, data, NoDiscrepancy()).model, mode="NUMBA")

    def residual(log_theta):
        theta = dict(zip(truth, np.exp(log_theta), strict=True))
        return (_step_response(rows, theta, np) - y) / 5e-4

    fit = least_squares(residual, np.log(list(truth.values())), x_scale=1e-3)
    reference = np.exp(fit.x)
    for seed in range(4):
        found = space.split(find_mode(space, seed=seed).value)
        bounds = [(p.args["lower"], p.args["upper"]) for p in priors.values()]
        theta = [lo + (hi - lo) / (1 + np.exp(-float(found[f"{n}_interval__"])))
                 for n, (lo, hi) in zip(truth, bounds, strict=True)]  # fmt: skip
        np.testing.assert_allclose(theta, reference, rtol=1e-3, err_msg=f"seed {seed}")


#: k + h fixed to 0.005 and h to 0.05: k's mode 0.06 lies 1.2 sds above its bound 0 and
#: h compensates it (correlation −0.995), like dielectric M2's ln γ and E_A
_K_H = (0.06, 0.0)


def _curved_ridge_with_partner_model():
    """The curved ridge of :func:`_curved_ridge_model`, and a pair (k, h) apart from it."""
    model = _curved_ridge_model()
    with model:
        k = pm.Uniform("k", 0.0, 1.0)
        h = pm.Normal("h", 0.0, 1.0)
        pm.Normal("y3", k + h, 0.005, observed=sum(_K_H))
        pm.Normal("y4", h, 0.05, observed=_K_H[1])
    return model


def _partner_reference():
    """Means and sds of k and h by quadrature (k in its box, h on a grid of 12 sds)."""
    k = np.linspace(0.0, 1.0, 20001)[:, None]
    h = np.linspace(-0.3, 0.3, 2401)[None, :]
    logp = -((k + h - sum(_K_H)) ** 2) / (2 * 0.005**2) - (h - _K_H[1]) ** 2 / (2 * 0.05**2)
    weight = np.exp(logp - logp.max() - h**2 / 2)
    weight /= weight.sum()
    out = {}
    for name, value in (("k", k), ("h", h)):
        mean = float((weight * value).sum())
        out[name] = (mean, float(np.sqrt((weight * (value - mean) ** 2).sum())))
    return out


def test_chained_bound_ridge_inverse_gradient_and_unit_jacobian():
    """Two bounded elements, the second following the first: inverse to 1e-10, the pulled-back
    gradient and det(∂w/∂u) = 1 against central differences, far from and past the bounds."""
    from kohpymc.ridge_curve import ChainedBoundRidge

    coords = Coordinates.identity(4)
    a = np.array([[1.0, 0.9, 0.5, 0.2], [0.9, 1.0, 0.5, 0.1], [0.5, 0.5, 1.0, 0.3]])
    cov = np.vstack([a, [0.2, 0.1, 0.3, 1.0]])
    mean = np.array([4.0, -4.0, 0.0, 1.0])
    ridge = ChainedBoundRidge.fit(coords, mean, cov, np.array([0, 1]), (np.zeros(2), np.ones(2)))
    rng = np.random.default_rng(SEED)
    for u in (mean + 0.1 * rng.normal(size=4), mean + 3.0 * rng.normal(size=4)):
        np.testing.assert_allclose(ridge.inverse(coords, ridge.forward(coords, u)), u, atol=1e-10)
        jac = np.column_stack(
            [(ridge.forward(coords, u + e) - ridge.forward(coords, u - e)) / 2e-6
             for e in 1e-6 * np.eye(4)]
        )  # fmt: skip
        g = rng.normal(size=4)
        np.testing.assert_allclose(ridge.pull_back(coords, u, g), jac.T @ g, rtol=1e-6, atol=1e-8)
        assert np.linalg.det(jac) == pytest.approx(1.0, abs=1e-6)
    # the second element follows the first's bend: beta[1, 0] is its regression on x_0
    assert ridge.beta[1, 0] != 0.0 and ridge.beta[0, 1] == ridge.beta[1, 1] == 0.0


def _drop_below(space, reparam, axis, at=-3.0):
    """Log density at z = 0 minus at z_axis = ``at`` (the others 0)."""
    z = np.zeros(reparam.ndim)
    z[axis] = at
    return reparam.logp_dlogp(space, np.zeros(reparam.ndim))[0] - reparam.logp_dlogp(space, z)[0]


def test_soft_box_partner_follows_a_parameter_near_its_bound(monkeypatch):
    """k in the soft box 1.2 sd above its bound with a partner h: without the bound ridge the
    partner keeps following k's unclipped coordinate past the bound, and the density 3 sd
    down k's axis (1.8 sd beyond the bound) drops by 95 (a wall; a Gaussian: 4.5); with
    it by < 10.  The map stays exact (gradient against finite differences, round trip)."""
    import kohpymc.ridge_curve as rc
    from kohpymc.reparameterization import log_coordinates

    space = value_space(_curved_ridge_with_partner_model())
    reparam = plan(space, seed=SEED)
    assert "ridge-curve-soft-box" in reparam.kind, reparam.reason
    assert "k, g near a bound" in reparam.reason, reparam.reason  # k nearest its bound first
    for z in (np.array([0.4, -1.1, 0.3, -2.0, 0.5]), np.array([-2.5, 2.0, -1.7, -3.5, 1.0])):
        logp = _check_plan_exact(space, reparam, z, rtol=1e-5, atol=1e-5, inverse_atol=1e-7)
        assert np.isfinite(logp)
    ridge = getattr(reparam, "inner", reparam)
    k_axis = 1 + list(ridge.rest).index(space.names.index("k_interval__"))
    with_ridge = _drop_below(space, ridge, k_axis)
    monkeypatch.setattr(rc, "_near_bound_ridge", lambda *args: None)
    laplace = _whitened(space, log_coordinates(space), reparam.mode.value, reparam.mode)
    without = _drop_below(space, rc.ridge_curve_plan(space, laplace, reparam.mode), k_axis)
    assert with_ridge < 10.0 < 50.0 < without, (with_ridge, without)


def _raw_quadratic():
    """y = a + b T + c T² in kelvin over 1000–1010 K (a Shomate-like fit, not centred):
    the unit-diagonal Hessian's eigenvalues span 4·10⁻¹², below what differences of a
    finite-difference gradient resolve.  Noise sd 0.2 known, uniform priors far from the
    posterior: the posterior is N(β̂, σ²(XᵀX)⁻¹) to within its truncation (nil here)."""
    from kohpymc import CalibrationData, PhysicsModel, Uniform

    T = np.repeat(np.linspace(1000.0, 1010.0, 11), 2)
    design = np.column_stack([np.ones_like(T), T, T**2])
    y = design @ [5e5, -1e3, 0.5] + np.random.default_rng(SEED).normal(0.0, 0.2, T.size)
    physics = PhysicsModel(
        lambda i, p: p["a"] + p["b"] * i["T"] + p["c"] * i["T"] ** 2,
        {"a": Uniform(0.0, 1e6), "b": Uniform(-2e3, 0.0), "c": Uniform(0.0, 1.0)},
        inputs=["T"],
    )
    mean = np.linalg.solve(design.T @ design, design.T @ y)
    cov = 0.2**2 * np.linalg.inv(design.T @ design)
    return physics, CalibrationData({"T": T}, y, noise_sd=0.2), mean, cov


def test_collinear_quadratic_in_natural_units_is_whitened_and_matches_the_exact_posterior():
    """Correlations −0.999999 between a, b, c: the Laplace covariance is measured again along
    provisionally whitened axes (before: no positive Hessian, PyMC's coordinates, r̂ 2.4 and
    161 divergences in 2 × 200 draws); the draws match the exact Gaussian posterior."""
    from kohpymc import NoDiscrepancy, calibrate

    physics, data, mean, cov = _raw_quadratic()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the identifiability report's practical-ridge note
        cal = calibrate(
            physics, data, NoDiscrepancy(), draws=1000, tune=1000, chains=2, random_seed=SEED
        )
    kind = json.loads(cal.idata.attrs["sampling"])["reparameterization"]["kind"]
    assert kind != "none"
    assert int(cal.idata.sample_stats.diverging.sum()) == 0
    for pair in ((0, 1), (1, 2)):
        names = tuple("abc"[i] for i in pair)
        _assert_moments(cal.idata, names, mean[list(pair)], cov[np.ix_(pair, pair)])


def _thermistor_case():
    """Steinhart–Hart T(R) = 1/(A + B ln R + C ln³ R) − 273.15 (a 10 kΩ NTC, A 1.1e-3,
    B 2.3e-4, C 8.8e-8 in 1/K) over 0–100 °C, R read to 0.01 Ω, noise 0.02 K unknown:
    the physics model and the data."""
    from kohpymc import CalibrationData, PhysicsModel, Uniform

    def celsius(R, p):
        L = np.log(R)
        return 1.0 / (p["A"] + p["B"] * L + p["C"] * L**3) - 273.15

    truth = {"A": 1.129e-3, "B": 2.341e-4, "C": 8.775e-8}
    T = np.linspace(0.0, 100.0, 21) + 273.15
    L = np.full_like(T, 9.0)
    for _ in range(50):  # ln R at each bath temperature, by Newton
        L -= (truth["A"] + truth["B"] * L + truth["C"] * L**3 - 1.0 / T) / (
            truth["B"] + 3 * truth["C"] * L**2
        )
    R = np.exp(L).round(2)
    rng = np.random.default_rng(11)
    rng.choice([3.3, 5.0], T.size)  # an unused supply-voltage column drew first
    y = (celsius(R, truth) + rng.normal(0.0, 0.02, T.size)).round(5)
    physics = PhysicsModel(
        lambda i, p: celsius(i["R"], p),
        {"A": Uniform(0.0, 3e-3), "B": Uniform(0.0, 5e-4), "C": Uniform(-5e-7, 5e-7)},
        inputs=["R"],
    )
    return physics, CalibrationData({"R": R}, y)


@functools.cache
def _thermistor_with_bias():
    """The thermistor under M1: a constant bias that the three nearly collinear coefficients
    almost absorb (value space)."""
    from kohpymc import ConstantBias
    from kohpymc.model import compose_model

    physics, data = _thermistor_case()
    return value_space(compose_model(physics, data, ConstantBias()).model)


@functools.cache
def _thermistor_plan():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return plan(_thermistor_with_bias(), seed=1)


def test_no_plan_leaves_an_axis_without_scale():
    """On the thermistor with a bias the ridge segment scored 0.28 against the affine map's
    25.7, but its position axis dropped 0.0 at ±3 (the map had lost that direction's scale):
    NUTS wandered along it, r̂ 1.28 and 201 divergences in 2 × 1000 draws.  Whatever plan is
    chosen, every axis's log density must change by ±3."""
    from kohpymc.reparameterization import _has_flat_axis

    space = _thermistor_with_bias()
    chosen = _thermistor_plan()
    assert not _has_flat_axis(space, chosen), chosen.kind


def test_thermistor_ridge_has_no_wall_within_three_sds():
    """The bias ridge ends where C reaches its upper prior bound, 3.1 Laplace sds from the
    mode.  Followed in PyMC's interval coordinates the map put a wall there (log density
    77 down at +3 sds along the followed axis, 4.5 for a Gaussian; 10 divergences, r̂ 1.019
    in 2 × 1000 draws).  Measured from C in its own units (a bound ridge) and followed along
    the ridge's own direction, every axis drops at most 9 at ±3 sds.  Followed as a ridge
    curve led by C's position in its box (the plan since C's box spanning zero no longer
    keeps the curve out), every axis across the ridge drops at most 9 at ±3 sds, and along
    it the map adds no wall: at ±3 its log density is within 0.5 of the conditional mode's
    (the posterior's own tail, 75.8 down at −3 where C nears −4·10⁻⁷, is no wall of the map;
    2 × 1000 draws: r̂ 1.002, ESS 802, no divergence)."""
    from kohpymc.bends import _conditional_mode
    from kohpymc.reparameterization import _axis_drops

    space = _thermistor_with_bias()
    chosen = _thermistor_plan()
    drops = _axis_drops(space, chosen, 3.0)
    assert np.all(drops > 1.0), (chosen.kind, drops)
    if "bound-ridge" in chosen.kind:
        assert np.all(drops < 9.0), (chosen.kind, drops)
        return
    # its pivot warped to normal quantiles since the affine pivot's axis fits badly
    # (Gaussian score 0.53 -> 0.038)
    assert chosen.kind == "ridge-curve-own-units-soft-box-warped", chosen.kind
    assert np.all(drops[1:] < 9.0), drops
    base, _ = chosen.logp_dlogp(space, np.zeros(chosen.ndim), safe=True)
    for side, at in enumerate((-3.0, 3.0)):
        mode = _conditional_mode(space, chosen, 0, at)
        mode[0] = at
        best = base - chosen.logp_dlogp(space, mode, safe=True)[0]
        assert drops[0, side] - best < 0.5, (at, drops[0, side], best)


def _thermistor_bias_reference():
    """Mean and sd of the bias δ and of σ_obs under M1, by quadrature over (δ, σ) on grids;
    (A, B, C) integrated out given them by Laplace on the least-squares fit (the model is
    linear in them over their conditional spread, 1e-5 relative), C's prior bounds as the
    Gaussian's mass between them."""
    from scipy.optimize import least_squares
    from scipy.stats import norm

    physics, data = _thermistor_case()
    L, y = np.log(np.asarray(data.inputs["R"], float)), np.asarray(data.y, float)
    X = np.column_stack([np.ones_like(L), L, L**3]) * np.array([1e-3, 1e-4, 1e-7])
    start = np.linalg.lstsq(X, 1.0 / (y + 273.15), rcond=None)[0]
    sd_y = y.std()  # the priors: δ ~ N(0, 2 sd(y)), σ ~ HalfNormal(sd(y))
    deltas = np.arange(-200.0, 200.01, 0.5)
    sigmas = np.exp(np.linspace(np.log(0.004), np.log(0.08), 300))
    logp = np.empty((deltas.size, sigmas.size))
    for i, delta in enumerate(deltas):

        def jac(p):
            return -((1.0 / (X @ p) ** 2)[:, None] * X)

        fit = least_squares(
            lambda p, d=delta: 1.0 / (X @ p) - 273.15 + d - y,
            start,
            jac=jac,
            method="lm",
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        jtj = jac(fit.x).T @ jac(fit.x)
        c_hat, c_sd = fit.x[2] * 1e-7, np.sqrt(np.linalg.inv(jtj)[2, 2]) * 1e-7
        mass = norm.cdf((5e-7 - c_hat) / (sigmas * c_sd)) - norm.cdf(
            (-5e-7 - c_hat) / (sigmas * c_sd)
        )
        logp[i] = (
            norm.logpdf(delta, 0.0, 2.0 * sd_y)
            + norm.logpdf(sigmas, 0.0, sd_y)
            - (y.size - 3) * np.log(sigmas)
            - np.sum(fit.fun**2) / (2.0 * sigmas**2)
            - 0.5 * np.linalg.slogdet(jtj)[1]
            + np.log(np.maximum(mass, np.finfo(float).tiny))
            + np.log(sigmas)  # the log-spaced grid
        )
    weights = np.exp(logp - logp.max())
    weights /= weights.sum()
    out = {}
    for name, grid, marginal in (
        ("delta", deltas, weights.sum(axis=1)),
        ("sigma_obs", sigmas, weights.sum(axis=0)),
    ):
        mean = float(marginal @ grid)
        out[name] = (mean, float(np.sqrt(marginal @ (grid - mean) ** 2)))
    return out


@pytest.mark.slow
def test_thermistor_with_bias_converges_to_quadrature():
    """Default settings (4 × (1000 + 1000)): r̂ ≤ 1.01, bulk ESS ≥ 400, and δ and σ_obs within
    4 Monte Carlo errors of quadrature (δ 38.7 ± 16.3 °C).  Measured: r̂ 1.003, ESS 1183,
    δ 39.6 ± 16.5, and 1 divergence in 4000 draws (A 2.6 and σ_obs 2.1 sds out, not at the
    ridge's end); issue 15 asks for none, this asserts at most 4 (0.1 %).  Before, the
    followed interval-coordinate map (the same data as a study, 2 × 1000, seed 2): r̂ 1.019,
    ESS 116, 10 divergences, δ 31.8 ± 14.2 (the upper tail, which C's prior bound ends at
    67 °C, under-sampled)."""
    from kohpymc import ConstantBias, calibrate

    physics, data = _thermistor_case()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = calibrate(physics, data, ConstantBias(), random_seed=SEED)
    idata = cal.idata
    names = ["A", "B", "C", "delta", "sigma_obs"]
    summary = az.summary(idata, var_names=names, kind="diagnostics")
    assert summary["r_hat"].max() <= 1.01 and summary["ess_bulk"].min() >= 400, summary
    assert int(idata.sample_stats.diverging.sum()) <= 4
    for name, (mean, sd) in _thermistor_bias_reference().items():
        draws = idata.posterior[name].values.ravel()
        ess = float(summary.loc[name, "ess_bulk"])
        assert abs(draws.mean() - mean) < 4 * sd / np.sqrt(ess), (name, draws.mean(), mean)
        assert abs(draws.std() / sd - 1) < 4 * np.sqrt(1 / (2 * ess)), (name, draws.std(), sd)
