"""Widths of the other coordinates scaled along a bent axis (:mod:`kohpymc.ridge_width`)."""

from dataclasses import replace

import numpy as np
import pymc as pm
import pytest

from kohpymc.bends import BentPlan, bend_coordinates
from kohpymc.reparameterization import _gaussian_score, plan
from kohpymc.ridge_width import Widths, transverse_error
from kohpymc.value_space import value_space
from tests.test_bends import _check_inverse_and_pull_back
from tests.test_reparameterization import (
    _assert_moments,
    _check_plan_exact,
    _finite_difference_gradient,
)

SEED = 20261127
KAPPA, NOISE, SPREAD = 2.0, 0.1, 0.6


def test_widths_inverse_gradient_and_log_jacobian():
    """Two scaled axes' splines (inside and beyond their nodes): inverse to 1e-12, the
    pulled-back gradient, and log|∂z'/∂z| and its gradient against central differences."""
    rng = np.random.default_rng(SEED)
    nodes = np.array([-3.0, -1.5, 0.0, 0.75, 1.5, 3.0])
    logs = rng.normal(scale=0.5, size=(2, nodes.size, 4))
    logs[:, 2, :] = 0.0
    logs[:, :, [0, 2]] = 0.0  # the bent axes 0 and 2 are not scaled
    widths = Widths((0, 2), nodes, logs)
    for u in (rng.normal(size=4), np.array([-4.2, 0.3, 3.7, -1.0])):
        jac = _check_inverse_and_pull_back(widths, u, rng)
        logjac, dlogjac = widths.log_jacobian(u)
        assert logjac == pytest.approx(np.log(np.linalg.det(jac)), abs=1e-6)
        fd = _finite_difference_gradient(lambda x: widths.log_jacobian(x)[0], u)
        np.testing.assert_allclose(dlogjac, fd, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(widths.forward(np.array([0.0, 0.7, 0.0, -2.0])), [0, 0.7, 0, -2])


def _noise_sd(x):
    return NOISE * np.exp(SPREAD * x)


def _narrowing_banana():
    """y − κx² measured with noise sd 0.1·e^{0.6x}, x from its N(0, 1) prior: a parabolic
    ridge whose width across changes 36-fold between x = −3 and 3."""
    with pm.Model() as model:
        x = pm.Normal("x", 0.0, 1.0)
        y = pm.Normal("y", 0.0, 10.0)
        pm.Normal("obs", y - KAPPA * x**2, _noise_sd(x), observed=[0.0])
    return model


def _narrowing_reference():
    """Means, covariance and excess kurtoses of (x, y) by quadrature in (x, s), with
    y = κx² + σ(x)·s: the density in (x, s) is e^{−x²/2 − y²/200 − s²/2} (σ(x) cancels)."""
    x, s = np.meshgrid(np.linspace(-7, 7, 2801), np.linspace(-8.0, 8.0, 641))
    y = KAPPA * x**2 + _noise_sd(x) * s
    logp = -0.5 * x**2 - 0.5 * (y / 10.0) ** 2 - 0.5 * s**2
    p = np.exp(logp - logp.max()).ravel()
    p /= p.sum()
    stacked = np.stack([x.ravel(), y.ravel()])
    mean = stacked @ p
    centred = stacked - mean[:, None]
    cov = (centred * p) @ centred.T
    return mean, cov, (centred**4 @ p) / np.diag(cov) ** 2 - 3.0


def _bent(space):
    """The affine Laplace plan bent (and widened) by :func:`~kohpymc.bends.bend_coordinates`."""
    reparam = plan(space, seed=SEED)
    plain = BentPlan(**{**reparam.__dict__, "bend": None, "squeeze": None, "kind": "affine"})
    return bend_coordinates(space, replace(plain, gaussian_score=_gaussian_score(space, plain)))


def _y_width(reparam, t):
    """How far y moves per unit of z_y at z = (t, 0), over y's exact conditional sd given x."""
    step = 1e-4
    x, low = reparam.to_value(np.array([t, -step]))
    _, high = reparam.to_value(np.array([t, step]))
    exact = 1.0 / np.sqrt(1.0 / _noise_sd(x) ** 2 + 1.0 / 100.0)
    return (high - low) / (2 * step) / exact


def test_ridge_that_narrows_gets_widths():
    """x's axis is bent and y's width scaled along it: across the ridge the drops at ±1.5 sds
    out at z_x = ±1.5, ±3 come within a tenth of the error they had, y's step per unit of
    z_y is its exact conditional sd within 10 % at z_x in [−3, 3] (without the widths 0.18
    to 5.6 times it), and the density in z has the gradient finite differences give and
    round trips."""
    space = value_space(_narrowing_banana())
    bent = _bent(space)
    assert bent.bend.axes == (0,) and bent.widths is not None
    without = replace(bent, widths=None)
    assert transverse_error(space, bent, (0,)) < 0.1 * transverse_error(space, without, (0,))
    grid = np.linspace(-3.0, 3.0, 25)
    ratios = np.array([_y_width(bent, t) for t in grid])
    assert np.all(np.abs(ratios - 1.0) < 0.1), ratios
    unscaled = np.array([_y_width(without, t) for t in grid])
    assert unscaled.min() < 0.3 and unscaled.max() > 3.0
    for z in (np.array([1.3, -0.4]), np.array([-2.7, 1.7]), np.array([5.1, 0.3])):
        _check_plan_exact(space, bent, z, rtol=1e-6, atol=1e-6, inverse_atol=1e-9)


def test_ridge_that_narrows_draws_match_quadrature():
    """Sampled with the widths (2 × (1000 + 1000), target acceptance 0.95): no divergences,
    and the mean, sd and correlation of (x, y) within 4 Monte Carlo errors of quadrature.
    Measured by hand (seeds 20261127 and 1): with the widths 4.6 / 4.5 leapfrog steps per
    draw and bulk ESS 1098 / 1202; the same bent plan without them 6.3 / 6.7 and 567 / 403."""
    from kohpymc.sampling import SamplingReport, _run_nutpie

    space = value_space(_narrowing_banana())
    settings = dict(draws=1000, tune=1000, chains=2, cores=1, seed=SEED)
    report = SamplingReport("nutpie", "nutpie")
    idata = _run_nutpie(space, _bent(space), settings, 0.95, False, {}, [], report)
    assert int(idata.sample_stats.diverging.sum()) == 0
    _assert_moments(idata, ("x", "y"), *_narrowing_reference())
