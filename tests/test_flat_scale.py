"""Bounded parameters on the scale of their flat prior, in a soft box (kohpymc.flat_scale)."""

from __future__ import annotations

import warnings

import arviz as az
import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import pytest

import kohpymc as kp
from kohpymc.flat_scale import SoftBoxShear, SoftFlatScaleCoordinates
from kohpymc.native import symbolic_value
from kohpymc.priors import LogUniform, Uniform
from kohpymc.reparameterization import Reparameterization, _axis_drops, plan
from kohpymc.value_space import value_space

R_GAS = 8.314
#: a rate law ``ln r = ln k0 − Ea/(R T) + m ln c``: linear in (ln k0, Ea, m), the scales on
#: which their priors are flat; over 300–340 K, ln k0 and Ea correlate at 0.998
T = np.repeat([300.0, 313.0, 326.0, 340.0], 6)
C = np.tile([0.1, 0.2, 0.4, 0.7, 1.2, 2.0], 4)
NOISE = 0.15
PRIORS = {"k0": LogUniform(3e11, 3e14), "Ea": Uniform(5e4, 1.2e5), "m": Uniform(0.0, 3.0)}


def _design() -> np.ndarray:
    return np.column_stack([np.ones_like(T), -1.0 / (R_GAS * T), np.log(C)])


def _data(seed: int = 5) -> np.ndarray:
    truth = np.array([np.log(1e13), 8.0e4, 1.2])
    return _design() @ truth + np.random.default_rng(seed).normal(0.0, NOISE, T.size)


def _reference(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact posterior mean and covariance of (ln k0, Ea, m): flat priors, known noise.

    The box truncates it 4.8 and 5.7 sds from the mean (ln k0), which moves the moments by
    less than 1e-5 sds.
    """
    x = _design()
    return np.linalg.lstsq(x, y, rcond=None)[0], NOISE**2 * np.linalg.inv(x.T @ x)


def _rate(inputs, params):
    temperature, conc = np.asarray(inputs["T"], float), np.asarray(inputs["c"], float)
    return np.log(params["k0"]) - params["Ea"] / (R_GAS * temperature) + params["m"] * np.log(conc)


def _coords() -> SoftFlatScaleCoordinates:
    return SoftFlatScaleCoordinates(
        np.array([True, False, False]),
        np.array([1e-11, 1.5e5, np.nan]),
        np.array([1e-8, 4.5e5, np.nan]),
        own=np.array([False, True, False]),
        width=np.array([0.15, 1.5e3, 1.0]),
    )


@pytest.mark.parametrize(
    "w",
    [
        [np.log(3e-10), 2.9e5, 0.3],  # inside
        [np.log(1.2e-11), 1.52e5, -1.0],  # a few widths inside the lower bounds
        [np.log(1e-8) + 0.2, 4.51e5, 2.0],  # beyond the upper bounds
    ],
)
def test_soft_box_derivatives_match_finite_differences(w):
    coords = _coords()
    w = np.array(w)
    v, dv, dlogjac, logjac = coords.to_value(w)
    steps = np.array([1e-6, 1e-1, 1e-6])
    for i, step in enumerate(steps):
        e = np.zeros(3)
        e[i] = step
        up, down = coords.to_value(w + e), coords.to_value(w - e)
        assert dv[i] == pytest.approx((up[0][i] - down[0][i]) / (2 * step), rel=1e-6)
        assert dlogjac[i] == pytest.approx((up[3] - down[3]) / (2 * step), rel=1e-5, abs=1e-12)
    np.testing.assert_allclose(coords.from_value(v), w, rtol=1e-12)
    values, total = coords.value_and_log_jacobian(w)
    np.testing.assert_allclose(values, v)
    assert total == pytest.approx(logjac)


def test_shear_map_symbolic_and_gradient_match_numpy():
    """The sheared map in PyTensor (nutpie's native path) is the numpy one; gradient exact."""
    coords = _coords()
    cov = np.array([[1.0, 0.6, 0.2], [0.6, 1.0, 0.1], [0.2, 0.1, 1.0]])
    shear = SoftBoxShear.fit(coords, np.zeros(3), cov, np.array([0]))
    coords = coords.with_ridge(shear)
    mean = np.array([np.log(1e-8) - 0.1, 2.9e5, 0.3])  # the bend is on beyond ln 1e-8
    chol = np.diag([0.3, 3e3, 1.0])
    reparam = Reparameterization("flat-scale-affine", mean, chol, coords, "")
    z, constants = pt.vector("z"), pt.vector("constants")  # h and β are inputs, not baked
    v, logjac = symbolic_value(reparam, z, constants=constants)
    f = pytensor.function([z, constants], [v, logjac], mode="FAST_COMPILE")
    grad = pytensor.grad(logjac + (v**2).sum(), z)
    g = pytensor.function([z, constants], grad, mode="FAST_COMPILE")
    numbers = reparam.map_constants()
    assert numbers.size == 3 + 3  # h of each element, β of the one sheared element
    for point in ([0.0, 0.0, 0.0], [1.5, -0.4, 0.7], [-2.0, 1.0, -1.0]):
        point = np.array(point)
        value, total = reparam.value_from_affine(mean + chol @ point)
        got_v, got_total = f(point, numbers)
        np.testing.assert_allclose(got_v, value, rtol=1e-12)
        assert float(got_total) == pytest.approx(float(total), rel=1e-12)
        np.testing.assert_allclose(reparam.from_value(value), point, atol=1e-9)
        u = mean + chol @ point
        w = shear.forward(coords, u)
        vv, dv, dlogjac, _ = coords.to_value(w)
        numpy_grad = chol.T @ reparam._pull_back(u, 2 * vv * dv + dlogjac)
        np.testing.assert_allclose(g(point, numbers), numpy_grad, rtol=1e-8, atol=1e-10)


def test_a_ridge_straight_in_natural_units_is_sampled_straight():
    """PyMC's interval transforms bend it; the flat-scale plan is Gaussian out to ±3 sds.

    Before: the whitened logit plan (score 0.018 at ±1.5 sds) dropped 7.3 and 8.2 at ∓3 sds
    along the ln k0 axis, where a Gaussian drops 4.5.
    """
    y = _data()
    with pm.Model() as model:
        k0, ea, m = (prior.create(name) for name, prior in PRIORS.items())
        mu = pt.log(k0) - ea / (R_GAS * T) + m * np.log(C)
        pm.Normal("y", mu, NOISE, observed=y)
    space = value_space(model)
    reparam = plan(space, seed=1)
    assert reparam.kind == "flat-scale-affine"
    np.testing.assert_allclose(_axis_drops(space, reparam, 3.0), 4.5, atol=0.05)
    mean, cov = _reference(y)
    value = reparam.to_value(np.zeros(3))
    share = 1.0 / (1.0 + np.exp(-value))
    x = space.lower + (space.upper - space.lower) * share
    np.testing.assert_allclose(
        (np.array([np.log(x[0]), *x[1:]]) - mean) / np.sqrt(np.diag(cov)), 0, atol=1e-3
    )


@pytest.mark.slow
def test_draws_along_a_straight_ridge_in_natural_units_match_the_exact_posterior():
    """kp.calibrate at defaults: no divergence, draws within Monte Carlo error of the exact.

    Before (PyMC's logit coordinates whitened): 16 divergences in 4 × 1000 draws.
    """
    y = _data()
    physics = kp.PhysicsModel(_rate, PRIORS, inputs=["T", "c"])
    data = kp.CalibrationData({"T": T, "c": C}, y, noise_sd=NOISE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = kp.calibrate(physics, data, random_seed=2026, check_identifiability=False)
    idata = result.idata
    assert int(idata.sample_stats.diverging.sum()) == 0
    assert float(az.rhat(idata).to_array().max()) <= 1.01
    post = idata.posterior
    draws = np.column_stack(
        [np.log(post["k0"].values).ravel(), post["Ea"].values.ravel(), post["m"].values.ravel()]
    )
    mean, cov = _reference(y)
    sd = np.sqrt(np.diag(cov))
    ess = float(az.ess(idata).to_array().min())
    assert ess >= 400
    np.testing.assert_array_less(np.abs(draws.mean(axis=0) - mean) / sd, 4.0 / np.sqrt(ess))
    np.testing.assert_array_less(np.abs(draws.std(axis=0) / sd - 1.0), 4.0 / np.sqrt(2 * ess))
    corr = np.corrcoef(draws[:, 0], draws[:, 1])[0, 1]
    assert corr == pytest.approx(cov[0, 1] / (sd[0] * sd[1]), abs=1e-3)
