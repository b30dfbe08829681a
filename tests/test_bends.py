"""A parabolic ridge followed by a quadratic (unit-triangular) map of the whitened coordinates."""

from dataclasses import replace

import arviz as az
import numpy as np
import pymc as pm
import pytensor.tensor as pt
import pytest

from kohpymc.bends import Bend, BentPlan, bend_plan
from kohpymc.native import PYTENSOR
from kohpymc.reparameterization import plan
from kohpymc.sampling import CURVED_TARGET_ACCEPT, sample_posterior, target_accept_for
from kohpymc.value_space import value_space
from tests.test_reparameterization import (
    _assert_moments,
    _check_plan_exact,
    _finite_difference_gradient,
)

SEED = 20261126
KAPPA, NOISE = 2.0, 0.1


def _random_bend(rng, n=4, bent=(1, 3)):
    chol = np.tril(rng.normal(size=(n, n))) + 3 * np.eye(n)
    coefs = rng.normal(size=(n, len(bent)))
    coefs[list(bent), :] = 0.0
    inverse = np.linalg.inv(chol)
    return Bend(rng.normal(size=n), inverse[list(bent)], chol @ coefs)


def _check_inverse_and_pull_back(m, u, rng):
    """``m.inverse`` undoes ``m.forward`` at ``u`` to 1e-12, and ``m.pull_back`` of the
    gradient of ``sin(a·forward(u))`` (``a`` drawn from ``rng``) matches central differences;
    returns ``∂ forward/∂u`` by central differences."""
    np.testing.assert_allclose(m.inverse(m.forward(u)), u, atol=1e-12)
    a = rng.normal(size=u.size)
    f = lambda x: float(np.sin(a @ m.forward(x)))  # noqa: E731
    grad_w = np.cos(a @ m.forward(u)) * a
    fd = _finite_difference_gradient(f, u)
    np.testing.assert_allclose(m.pull_back(u, grad_w), fd, rtol=1e-6, atol=1e-8)
    return np.column_stack(
        [(m.forward(u + e) - m.forward(u - e)) / 2e-6 for e in 1e-6 * np.eye(u.size)]
    )


def test_bend_inverse_gradient_and_unit_jacobian():
    """Inverse to 1e-12; the pulled-back gradient of a test function and det(∂u'/∂u) = 1
    against central differences; the PyTensor form gives the same values."""
    rng = np.random.default_rng(SEED)
    bend = _random_bend(rng)
    u = rng.normal(size=4)
    jac = _check_inverse_and_pull_back(bend, u, rng)
    assert np.linalg.det(jac) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(bend.forward(pt.as_tensor(u), PYTENSOR).eval(), bend.forward(u))


def _banana():
    """y − κx² measured to 0.1, x from its N(0, 1) prior: a parabola 20 widths deep at x = 1."""
    with pm.Model() as model:
        x = pm.Normal("x", 0.0, 1.0)
        y = pm.Normal("y", 0.0, 10.0)
        pm.Normal("obs", y - KAPPA * x**2, NOISE, observed=[0.0])
    return model


def _banana_reference(cubic=0.0, kurtosis=False, path=None):
    """Mean and covariance of (x, y) by quadrature in (x, r = y − κx² − cubic·x³), and
    with ``kurtosis`` their excess kurtoses; ``path(x)`` replaces κx² + cubic·x³."""
    x, r = np.meshgrid(np.linspace(-7, 7, 2801), np.linspace(-1.0, 1.0, 801))
    y = r + (KAPPA * x**2 + cubic * x**3 if path is None else path(x))
    logp = -0.5 * x**2 - 0.5 * (y / 10.0) ** 2 - 0.5 * (r / NOISE) ** 2
    p = np.exp(logp - logp.max()).ravel()
    p /= p.sum()
    stacked = np.stack([x.ravel(), y.ravel()])
    mean = stacked @ p
    centred = stacked - mean[:, None]
    cov = (centred * p) @ centred.T
    if not kurtosis:
        return mean, cov
    return mean, cov, (centred**4 @ p) / np.diag(cov) ** 2 - 3.0


def test_banana_is_bent_exactly():
    """The planner bends the banana's x axis (Gaussian score from > 10 to < 0.1: the rest is the
    x-marginal's own quartic term from y's prior); the
    density in z has the gradient finite differences give and z ↔ v round trips."""
    space = value_space(_banana())
    reparam = plan(space, seed=SEED)
    assert isinstance(reparam, BentPlan) and reparam.kind == "bent-affine", reparam.reason
    assert "bent along the parabola" in reparam.reason
    unbent = bend_plan(space, reparam)  # a bent plan is not bent again
    assert unbent is None
    plain = BentPlan(**{**reparam.__dict__, "bend": None})
    from kohpymc.reparameterization import _gaussian_score

    assert _gaussian_score(space, plain) > 10 and reparam.gaussian_score < 0.1
    z = np.array([1.3, -0.4])
    _check_plan_exact(space, reparam, z, rtol=1e-6, atol=1e-7, inverse_atol=1e-10)


def test_curve_bend_inverse_gradient_and_unit_jacobian():
    """A spline path per bent axis (inside and beyond its nodes) and a bilinear term between
    two bent axes: inverse to 1e-12, pulled-back gradient and det(∂z'/∂z) = 1 against central
    differences."""
    from kohpymc.bends import CurveBend

    rng = np.random.default_rng(SEED)
    nodes = np.array([-3.0, -1.5, 0.0, 1.5, 3.0])
    shifts = rng.normal(size=(2, nodes.size, 4))
    shifts[:, 2, :] = 0.0
    shifts[:, :, [0, 2]] = 0.0  # the bent axes 0 and 2 are not moved
    cross = rng.normal(size=4)
    cross[[0, 2]] = 0.0
    bend = CurveBend((0, 2), nodes, shifts, ((0, 1, cross),))
    for u in (rng.normal(size=4), np.array([4.2, -0.3, -3.7, 1.0])):
        jac = _check_inverse_and_pull_back(bend, u, rng)
        assert np.linalg.det(jac) == pytest.approx(1.0, abs=1e-6)


def test_any_plan_is_bent_in_its_own_coordinates():
    """bend_coordinates bends a plan through its ``z`` alone (here an unbent whitened plan
    wrapped as a black box): the banana's score falls as with bend_plan, the density in the
    bent z has the gradient finite differences give, and z ↔ v round trips."""
    from kohpymc.bends import BentCoordinatesPlan, bend_coordinates
    from kohpymc.reparameterization import _gaussian_score

    space = value_space(_banana())
    reparam = plan(space, seed=SEED)
    plain = BentPlan(**{**reparam.__dict__, "bend": None, "kind": "affine"})
    plain = replace(plain, gaussian_score=_gaussian_score(space, plain))
    bent = bend_coordinates(space, plain)
    assert isinstance(bent, BentCoordinatesPlan) and bent.kind == "bent-affine"
    assert plain.gaussian_score > 10 and bent.gaussian_score < 0.1
    for z in (np.array([1.3, -0.4]), np.array([-2.2, 1.7])):
        _check_plan_exact(space, bent, z, rtol=1e-6, atol=1e-7, inverse_atol=1e-10)


def test_banana_draws_match_quadrature_without_divergences():
    """Sampled bent: no divergences, and the mean, sd and correlation of (x, y) match
    quadrature within 4 Monte Carlo errors."""
    idata, report = sample_posterior(_banana(), draws=1000, tune=1000, chains=2, random_seed=SEED)
    assert report.reparameterization["kind"] == "bent-affine", report
    assert int(idata.sample_stats.diverging.sum()) == 0
    _assert_moments(idata, ("x", "y"), *_banana_reference())  # x, y uncorrelated: ρ = 0


def test_squeeze_inverse_gradient_and_log_jacobian():
    """Inverse to 1e-12; the pulled-back gradient and log|det ∂u'/∂u| against central
    differences; the PyTensor forms give the same values."""
    from kohpymc.bends import Squeeze

    rng = np.random.default_rng(SEED)
    chol = np.tril(rng.normal(size=(3, 3))) + 3 * np.eye(3)
    inverse = np.linalg.inv(chol)
    squeeze = Squeeze(rng.normal(size=3), inverse[[0, 2]], chol[:, [0, 2]], np.array([0.7, 2.0]))
    u = squeeze.centre + chol @ np.array([2.5, -0.3, -3.1])
    jac = _check_inverse_and_pull_back(squeeze, u, rng)
    assert squeeze.log_jacobian(u) == pytest.approx(np.log(np.linalg.det(jac)), abs=1e-6)
    _, dlog = squeeze.derivatives(u)
    fd_log = _finite_difference_gradient(squeeze.log_jacobian, u)
    np.testing.assert_allclose(squeeze.rows.T @ dlog, fd_log, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(
        squeeze.forward(pt.as_tensor(u), PYTENSOR).eval(), squeeze.forward(u), rtol=1e-12
    )
    assert float(squeeze.log_jacobian(pt.as_tensor(u), PYTENSOR).eval()) == pytest.approx(
        squeeze.log_jacobian(u)
    )


QUARTIC = 0.3


def _light_banana():
    """The banana with a light-tailed x: log p(x) = −x²/2 − 0.3 x⁴."""
    with pm.Model() as model:
        x = pm.Normal("x", 0.0, 1.0)
        y = pm.Normal("y", 0.0, 10.0)
        pm.Potential("light", -QUARTIC * x**4)
        pm.Normal("obs", y - KAPPA * x**2, NOISE, observed=[0.0])
    return model


def _light_banana_reference():
    x, r = np.meshgrid(np.linspace(-5, 5, 2001), np.linspace(-1.0, 1.0, 801))
    y = r + KAPPA * x**2
    logp = -0.5 * x**2 - QUARTIC * x**4 - 0.5 * (y / 10.0) ** 2 - 0.5 * (r / NOISE) ** 2
    p = np.exp(logp - logp.max()).ravel()
    p /= p.sum()
    out = {}
    for name, value in (("x", x.ravel()), ("y", y.ravel())):
        mean = float(value @ p)
        out[name] = (mean, float(np.sqrt(((value - mean) ** 2) @ p)))
    return out


def test_light_tailed_axis_is_squeezed_and_sampled_exactly():
    """x's whitened axis drops ~30 at ±3 sd after the bend (4.5 for a Gaussian): the plan
    squeezes it (drop within 1 of 4.5), its density has the gradient finite differences
    give and round trips; the draws' means and sds match quadrature within 4 Monte Carlo
    errors, without divergences."""
    from kohpymc.bends import _drops

    model = _light_banana()
    space = value_space(model)
    reparam = plan(space, seed=SEED)
    assert reparam.kind == "squeezed-bent-affine", reparam.reason
    assert abs(_drops(space, reparam, 0) - 4.5) < 1.0
    unsqueezed = BentPlan(**{**reparam.__dict__, "squeeze": None})
    assert _drops(space, unsqueezed, 0) > 9.0
    z = np.array([2.3, -0.4])
    _check_plan_exact(space, reparam, z, rtol=1e-6, atol=1e-7, inverse_atol=1e-10)
    idata, report = sample_posterior(model, draws=1000, tune=1000, chains=2, random_seed=SEED)
    assert report.reparameterization["kind"] == "squeezed-bent-affine", report
    assert int(idata.sample_stats.diverging.sum()) == 0
    ess = float(az.ess(idata, var_names=["x", "y"]).to_array().min())
    assert ess > 400
    for name, (mean, sd) in _light_banana_reference().items():
        draws = idata.posterior[name].values.ravel()
        assert abs(draws.mean() - mean) < 4 * sd / np.sqrt(ess), name
        assert abs(draws.std(ddof=1) / sd - 1) < 4 / np.sqrt(2 * ess), name


# ------------------------------------------- a ridge that bends faster than a parabola
CUBIC = 1.0


def _cubic_banana():
    """y − κx² − cx³ measured to 0.1, x from its N(0, 1) prior: the ridge's path has an odd
    part, which no parabola through its conditional modes at ±1.5 sd follows."""
    with pm.Model() as model:
        x = pm.Normal("x", 0.0, 1.0)
        y = pm.Normal("y", 0.0, 10.0)
        pm.Normal("obs", y - KAPPA * x**2 - CUBIC * x**3, NOISE, observed=[0.0])
    return model


def test_fast_bending_ridge_is_followed_exactly():
    """No parabola helps (the plan was PyMC's coordinates, Gaussian score 40.8); the planner
    follows x's axis along the conditional modes (score < 0.2), and the density in z has
    the gradient finite differences give and z ↔ v round trips."""
    from kohpymc.bends import BentCoordinatesPlan

    space = value_space(_cubic_banana())
    reparam = plan(space, seed=SEED)
    assert isinstance(reparam, BentCoordinatesPlan), reparam.reason
    assert reparam.kind == "followed-affine" and reparam.gaussian_score < 0.2
    assert "followed along the path" in reparam.reason
    for z in (np.array([1.3, -0.4]), np.array([-2.7, 0.8])):
        _check_plan_exact(space, reparam, z, rtol=1e-6, atol=1e-6, inverse_atol=1e-9)
    # a curved plan is sampled at 0.95 unless the caller says otherwise
    assert target_accept_for(reparam, None) == CURVED_TARGET_ACCEPT == 0.95
    assert target_accept_for(reparam, 0.8) == 0.8
    assert target_accept_for(reparam.inner, None) == 0.9


@pytest.mark.parametrize("seed", [SEED, 1])
def test_fast_bending_ridge_draws_match_quadrature(seed):
    """Before, sampled in PyMC's coordinates: 105 divergences in 2 × (1000 + 1000), bulk ESS
    12, r̂ 1.12, y's sd 0.46 against 2.33.  Followed: no divergences (at target acceptance
    0.9 there were 1 and 3 at these seeds, 0.95 is the default on a curved plan), and the
    mean, sd and correlation of (x, y) match quadrature within 4 Monte Carlo errors (y's
    excess kurtosis is 17.6: its sd's Monte Carlo error is 3.1× a Gaussian's)."""
    idata, report = sample_posterior(
        _cubic_banana(), draws=1000, tune=1000, chains=2, random_seed=seed
    )
    assert report.reparameterization["kind"] == "followed-affine", report
    assert report.target_accept == CURVED_TARGET_ACCEPT
    assert int(idata.sample_stats.diverging.sum()) == 0
    _assert_moments(idata, ("x", "y"), *_banana_reference(CUBIC, kurtosis=True))


# ------------------------------------------- a ridge that turns between the bend's nodes
HINGE_SLOPE, HINGE_KNEE, HINGE_WIDTH = 2.0, 0.7, 0.1


def _hinge(x, softplus=np.logaddexp):
    """``s·w·softplus((x − x₀)/w)``: flat at the mode, slope s beyond a knee between 0 and 1.5."""
    return HINGE_SLOPE * HINGE_WIDTH * softplus(0.0, (x - HINGE_KNEE) / HINGE_WIDTH)


def _hinged_ridge():
    """y − hinge(x) measured to 0.1, x from its N(0, 1) prior: y's conditional mode stays at 0
    up to x ≈ 0.5 and then climbs 2 per sd of x (16 widths at x = 1.5)."""
    with pm.Model() as model:
        x = pm.Normal("x", 0.0, 1.0)
        y = pm.Normal("y", 0.0, 10.0)
        pm.Normal("obs", y - _hinge(x, lambda a, b: pt.softplus(b)), NOISE, observed=[0.0])
    return model


def _hinge_plan(space):
    """The affine Laplace plan bent by :func:`~kohpymc.bends.bend_coordinates`."""
    from kohpymc.bends import bend_coordinates
    from kohpymc.reparameterization import _gaussian_score

    reparam = plan(space, seed=SEED)
    plain = BentPlan(**{**reparam.__dict__, "bend": None, "squeeze": None, "kind": "affine"})
    plain = replace(plain, gaussian_score=_gaussian_score(space, plain))
    return plain, bend_coordinates(space, plain)


def _path_miss(reparam, t):
    """Where ``reparam`` puts y at ``z = (t, 0)``, from the exact conditional mode of y given
    x (the likelihood's ``hinge(x)`` shrunk by y's N(0, 10) prior), in conditional sds."""
    x, y = reparam.to_value(np.array([t, 0.0]))
    return (y - _hinge(x) / (1.0 + (NOISE / 10.0) ** 2)) / NOISE


def test_path_that_turns_between_nodes_gets_more_nodes():
    """The bent path stays within 0.5 conditional sd of y's exact conditional mode at every
    z_x in [−3, 3] (step 0.05).  Through the default nodes alone (±1.5 sds apart) the spline
    misses the knee by 3.7 sds, although the Gaussian score, which probes the nodes, is as
    low (< 0.01) as with the added ones."""
    from kohpymc.bends import _CURVE_NODES, CurveBend, _mode_path
    from kohpymc.reparameterization import _gaussian_score

    space = value_space(_hinged_ridge())
    plain, bent = _hinge_plan(space)
    grid = np.linspace(-3.0, 3.0, 121)
    assert plain.gaussian_score > 10 and bent.gaussian_score < 0.01
    assert bent.bend.nodes.size > _CURVE_NODES.size
    assert max(abs(_path_miss(bent, t)) for t in grid) < 0.5
    coarse = CurveBend((0,), _CURVE_NODES.copy(), _mode_path(space, plain, 0, [0])[None])
    coarse_plan = replace(bent, bend=coarse)
    assert max(abs(_path_miss(coarse_plan, t)) for t in grid) > 2.0
    assert _gaussian_score(space, coarse_plan) < 0.01
    for z in (np.array([0.8, -0.4]), np.array([-2.2, 1.7])):
        _check_plan_exact(space, bent, z, rtol=1e-6, atol=1e-6, inverse_atol=1e-9)


def test_path_that_turns_between_nodes_draws_match_quadrature():
    """Sampled along the refined path (2 × (1000 + 1000), target acceptance 0.95): no
    divergences, and the mean, sd and correlation of (x, y) within 4 Monte Carlo errors of
    quadrature."""
    from kohpymc.sampling import SamplingReport, _run_nutpie

    space = value_space(_hinged_ridge())
    settings = dict(draws=1000, tune=1000, chains=2, cores=1, seed=SEED)
    report = SamplingReport("nutpie", "nutpie")
    bent = _hinge_plan(space)[1]
    idata = _run_nutpie(space, bent, settings, 0.95, False, {}, [], report)
    assert int(idata.sample_stats.diverging.sum()) == 0
    _assert_moments(idata, ("x", "y"), *_banana_reference(kurtosis=True, path=_hinge))


# ------------------------------------- two axes that move a third jointly (pair surfaces)
TWIST = 3.0


def test_pair_surface_inverse_gradient_and_unit_jacobian():
    """A bent axis (0), a partner (1) moved by the bent path, and a surface over the two
    that moves the rest: inverse to 1e-12 (inside and beyond the surface's nodes), the
    pulled-back gradient and det(∂z'/∂z) = 1 against central differences."""
    from kohpymc.bends import CurveBend, PairSurface

    rng = np.random.default_rng(SEED)
    nodes = np.array([-3.0, -1.5, 0.0, 1.5, 3.0])
    shifts = rng.normal(size=(1, nodes.size, 4))
    shifts[:, 2, :], shifts[:, :, 0] = 0.0, 0.0  # the path moves the partner 1 too
    values = rng.normal(size=(nodes.size, nodes.size, 4))
    values[2, :, :], values[:, 2, :], values[:, :, [0, 1]] = 0.0, 0.0, 0.0
    surface = PairSurface(0, 1, nodes, values)
    bend = CurveBend((0,), nodes, shifts, surfaces=(surface,))
    for u in (rng.normal(size=4), np.array([-4.2, 3.6, -0.3, 1.0])):
        jac = _check_inverse_and_pull_back(bend, u, rng)
        assert np.linalg.det(jac) == pytest.approx(1.0, abs=1e-6)
    # the surface vanishes along either axis alone and interpolates its grid
    np.testing.assert_allclose(surface.value(np.array([2.2, 0.0, 0.5, 0.5])), 0.0, atol=1e-14)
    np.testing.assert_allclose(surface.value(np.array([0.0, -0.7, 0.5, 0.5])), 0.0, atol=1e-14)
    np.testing.assert_allclose(surface.value(np.array([-1.5, 3.0, 0.0, 0.0])), values[1, 4])


def _twisted_banana():
    """y − κx² − c·x·g measured to 0.1, x and g from N(0, 1) priors: along x's axis y follows
    a parabola, and x and g jointly move y (by 120 widths at x = g = 2) — along g alone not."""
    with pm.Model() as model:
        x = pm.Normal("x", 0.0, 1.0)
        g = pm.Normal("g", 0.0, 1.0)
        y = pm.Normal("y", 0.0, 10.0)
        pm.Normal("obs", y - KAPPA * x**2 - TWIST * x * g, NOISE, observed=[0.0])
    return model


def _twisted_reference():
    """Means, covariance and excess kurtoses of (x, g, y) by quadrature in (x, g, r)."""
    axis = np.linspace(-6.0, 6.0, 241)
    x, g, r = np.meshgrid(axis, axis, np.linspace(-0.6, 0.6, 97), indexing="ij")
    y = r + KAPPA * x**2 + TWIST * x * g
    logp = -0.5 * (x**2 + g**2) - 0.5 * (y / 10.0) ** 2 - 0.5 * (r / NOISE) ** 2
    p = np.exp(logp - logp.max()).ravel()
    p /= p.sum()
    stacked = np.stack([x.ravel(), g.ravel(), y.ravel()])
    mean = stacked @ p
    centred = stacked - mean[:, None]
    cov = (centred * p) @ centred.T
    return mean, cov, (centred**4 @ p) / np.diag(cov) ** 2 - 3.0


def _twisted_plan(space):
    """The affine Laplace plan bent by :func:`~kohpymc.bends.bend_coordinates`."""
    from kohpymc.bends import bend_coordinates
    from kohpymc.reparameterization import _gaussian_score

    reparam = plan(space, seed=SEED)
    plain = BentPlan(**{**reparam.__dict__, "bend": None, "squeeze": None, "kind": "affine"})
    return bend_coordinates(space, replace(plain, gaussian_score=_gaussian_score(space, plain)))


def test_two_axes_moving_a_third_get_a_pair_surface():
    """x's axis is bent and (x, g) get a surface: their joint drop at (±2, ±2) sds, which
    misses the sum of their own by > 100 without it, is then additive within 1 (y's prior); the
    density in z has the gradient finite differences give and z ↔ v round trips."""
    from kohpymc.bends import _joint_excess

    space = value_space(_twisted_banana())
    bent = _twisted_plan(space)
    assert bent.bend.axes == (0,)
    assert [(s.k, s.j) for s in bent.bend.surfaces] == [(0, 1)]
    without = replace(bent, bend=replace(bent.bend, surfaces=()))
    assert _joint_excess(space, without, 0, 1) > 100
    assert _joint_excess(space, bent, 0, 1) < 1.0  # the rest: y's N(0, 10) prior
    for z in (np.array([1.3, -0.4, 0.2]), np.array([-2.2, -3.7, 1.1])):
        _check_plan_exact(space, bent, z, rtol=1e-6, atol=1e-6, inverse_atol=1e-9)


def test_pair_surface_draws_match_quadrature():
    """Sampled with the surface (2 × (1000 + 1000), target acceptance 0.95): no divergences,
    and the mean, sd and correlation of (x, y) and (g, y) within 4 Monte Carlo errors of
    quadrature.  Measured by hand (seeds 1, 2, not this test's): without the surface (the
    bent path alone) 101 leapfrog steps per draw, bulk ESS 367 / 308 and y's sd 0.95 / 0.91
    of quadrature's 3.00; with it 7.1 / 7.0 steps, ESS 893 / 905, y's sd 0.98 / 1.01."""
    from kohpymc.sampling import SamplingReport, _run_nutpie

    space = value_space(_twisted_banana())
    settings = dict(draws=1000, tune=1000, chains=2, cores=1, seed=SEED)
    report = SamplingReport("nutpie", "nutpie")
    idata = _run_nutpie(space, _twisted_plan(space), settings, 0.95, False, {}, [], report)
    assert int(idata.sample_stats.diverging.sum()) == 0
    mean, cov, kurtosis = _twisted_reference()
    for pair in ([0, 2], [1, 2]):
        names = tuple(np.array(["x", "g", "y"])[pair])
        _assert_moments(idata, names, mean[pair], cov[np.ix_(pair, pair)], kurtosis[pair])
