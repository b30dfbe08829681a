"""Multi-start least squares: recovery against independent optima, search boxes, bad input.

The references are computed here without the module: profile likelihoods (the linear
amplitude solved in closed form) minimised on fine grids and by ``minimize_scalar``,
scipy quantiles for the prior boxes.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from scipy.optimize import least_squares, minimize_scalar

from kohpymc import (
    CalibrationData,
    Custom,
    HalfNormal,
    LogNormal,
    Normal,
    PhysicsModel,
    PhysicsModelError,
    Uniform,
)
from kohpymc.initialization import multistart_least_squares, prior_box

#: seed of the synthetic data in this file
SEED = 314


# ------------------------------------------------------------------ exponential decay
def _decay(x, p):
    return p["A"] * np.exp(-x["t"] / p["tau"])


@pytest.fixture(scope="module")
def decay_problem():
    """y = A exp(-t/τ) + noise, A ~ 1e3 and τ ~ 1e-3 in natural units."""
    physics = PhysicsModel(
        _decay, {"A": Uniform(100.0, 1e4), "tau": LogNormal(np.log(1e-3), 1.0)}, inputs=["t"]
    )
    t = np.linspace(0.0, 6e-3, 40)
    rng = np.random.default_rng(SEED)
    y = _decay({"t": t}, {"A": 1.5e3, "tau": 1.2e-3}) + rng.normal(0.0, 2.0, t.size)
    return physics, CalibrationData({"t": t}, y, noise_sd=2.0)


def _decay_optimum(t, y):
    """Global least-squares optimum by profiling out A (linear) over a fine grid in ln τ."""

    def profile(log_tau):
        g = np.exp(-t / np.exp(log_tau))
        amp = (g @ y) / (g @ g)
        return float(np.sum((amp * g - y) ** 2)), amp

    grid = np.linspace(np.log(1e-5), np.log(1e-1), 4001)
    i = int(np.argmin([profile(v)[0] for v in grid]))
    res = minimize_scalar(
        lambda v: profile(v)[0],
        bounds=(grid[i - 1], grid[i + 1]),
        method="bounded",
        options={"xatol": 1e-12},
    )
    return profile(res.x)[1], float(np.exp(res.x)), profile(res.x)[0]


@pytest.mark.parametrize("log_stage", [False, True])
def test_exponential_decay_across_orders_of_magnitude(decay_problem, log_stage):
    physics, data = decay_problem
    amp, tau, ssr = _decay_optimum(data.inputs["t"], data.y)
    kwargs = {}
    if log_stage:  # screening on log outputs, the data floored at the noise level
        kwargs = {
            "transform": lambda g: np.log(np.maximum(g, 1e-300)),
            "data_transform": lambda v: np.log(np.maximum(v, data.noise_sd)),
        }
    fit = multistart_least_squares(physics, data, starts=8, seed=1, **kwargs)
    assert fit.params["A"] == pytest.approx(amp, rel=1e-5)
    assert fit.params["tau"] == pytest.approx(tau, rel=1e-5)
    assert fit.cost == pytest.approx(0.5 * ssr / data.noise_sd**2, rel=1e-8)
    assert fit.starts.shape == fit.fits.shape == (8, 2) and fit.start_costs.shape == (8,)
    assert np.all((fit.starts >= fit.lower) & (fit.starts <= fit.upper))
    if not log_stage:  # the best start is the fit
        assert min(fit.start_costs) == fit.cost


def test_same_seed_same_fit_and_starts_differ_by_seed(decay_problem):
    physics, data = decay_problem
    a = multistart_least_squares(physics, data, starts=3, seed=5)
    b = multistart_least_squares(physics, data, starts=3, seed=5)
    c = multistart_least_squares(physics, data, starts=3, seed=6)
    assert a.params == b.params and np.array_equal(a.starts, b.starts)
    assert not np.array_equal(a.starts, c.starts)


# ------------------------------------------------------------------ bimodal surface
_WIDTH = 0.5


def _bump(x, p):
    return p["A"] * np.exp(-0.5 * ((x["x"] - p["c"]) / _WIDTH) ** 2)


@pytest.fixture(scope="module")
def bimodal_problem():
    """A tall peak at +2 and a lower one at -2, fitted with a single bump (A, c)."""
    x = np.linspace(-6.0, 6.0, 121)
    rng = np.random.default_rng(SEED + 1)
    y = _bump({"x": x}, {"A": 1.0, "c": 2.0}) + _bump({"x": x}, {"A": 0.6, "c": -2.0})
    y = y + rng.normal(0.0, 0.02, x.size)
    physics = PhysicsModel(_bump, {"A": Uniform(0.0, 2.0), "c": Uniform(-5.0, 3.0)}, inputs=["x"])
    return physics, CalibrationData({"x": x}, y, noise_sd=0.02)


def _bimodal_grid_minimum(x, y):
    """Brute force: c on a 1e-4 grid, A profiled in closed form (clipped to its prior)."""
    c = np.arange(-5.0, 3.0 + 5e-5, 1e-4)
    best = (np.inf, None, None)
    for chunk in np.array_split(c, 40):
        g = np.exp(-0.5 * ((x[None, :] - chunk[:, None]) / _WIDTH) ** 2)
        amp = np.clip((g @ y) / np.sum(g * g, axis=1), 0.0, 2.0)
        ssr = np.sum((amp[:, None] * g - y[None, :]) ** 2, axis=1)
        i = int(np.argmin(ssr))
        if ssr[i] < best[0]:
            best = (float(ssr[i]), float(amp[i]), float(chunk[i]))
    return best


def test_bimodal_surface_multistart_finds_the_global_minimum(bimodal_problem):
    physics, data = bimodal_problem
    x, y, sd = data.inputs["x"], data.y, data.noise_sd
    ssr, amp, c = _bimodal_grid_minimum(x, y)
    assert c == pytest.approx(2.0, abs=0.05)

    # one local fit from the prior centre (A, c) = (1, -1) ends in the other basin
    def residual(v):
        return (_bump({"x": x}, {"A": v[0], "c": v[1]}) - y) / sd

    single = least_squares(residual, [1.0, -1.0], bounds=([0.0, -5.0], [2.0, 3.0]))
    assert single.x[1] == pytest.approx(-2.0, abs=0.1)
    assert single.cost > 2.0 * 0.5 * ssr / sd**2  # the lower peak: ~3x the global cost

    fit = multistart_least_squares(physics, data, starts=8, seed=0)
    assert fit.params["c"] == pytest.approx(c, abs=2e-4)
    assert fit.params["A"] == pytest.approx(amp, abs=1e-3)
    assert fit.cost <= 0.5 * ssr / sd**2 * (1 + 1e-6)
    # some starts did end in the other basin: the design matters, not luck of one start
    assert np.any(np.abs(fit.fits[:, 1] + 2.0) < 0.1)


def test_failing_model_regions_are_avoided(bimodal_problem):
    _, data = bimodal_problem

    def fragile(x, p):
        if p["A"] > 1.8:
            raise RuntimeError("solver diverged")
        return _bump(x, p) if p["c"] < 2.8 else np.full(x["x"].size, np.nan)

    physics = PhysicsModel(fragile, {"A": Uniform(0.0, 2.0), "c": Uniform(-5.0, 3.0)}, inputs=["x"])
    fit = multistart_least_squares(physics, data, starts=8, seed=0)
    assert fit.params["c"] == pytest.approx(2.0, abs=0.01)

    def broken(x, p):
        raise RuntimeError("always")

    physics = PhysicsModel(broken, {"A": Uniform(0.0, 2.0)}, inputs=["x"])
    with pytest.raises(PhysicsModelError, match="all 2 start"):
        multistart_least_squares(physics, data, starts=2)


# ------------------------------------------------------------------ boxes, bad input
def test_prior_box_uses_support_or_central_quantiles():
    physics = PhysicsModel(
        lambda x, p: x["t"],
        {
            "u": Uniform(-1.0, 4.0),
            "n": Normal(3.0, 2.0),
            "ln": LogNormal(-7.0, 0.5),
            "hn": HalfNormal(5.0),
            "c": Custom(lambda name, **kw: None, mean=10.0, scale=2.0),
        },
        inputs=["t"],
    )
    box = prior_box(physics, coverage=0.95)
    assert box["u"] == (-1.0, 4.0)
    np.testing.assert_allclose(box["n"], stats.norm.ppf([0.025, 0.975], 3.0, 2.0), rtol=1e-12)
    np.testing.assert_allclose(
        box["ln"], stats.lognorm.ppf([0.025, 0.975], 0.5, scale=np.exp(-7.0)), rtol=1e-10
    )
    np.testing.assert_allclose(box["hn"], stats.halfnorm.ppf([0.025, 0.975], scale=5.0))
    assert box["c"] == (4.0, 16.0)
    assert prior_box(physics, bounds={"n": (0.0, 1.0)})["n"] == (0.0, 1.0)


def test_bad_input_raises_clear_errors(decay_problem):
    physics, data = decay_problem
    with pytest.raises(ValueError, match="starts must be >= 1"):
        multistart_least_squares(physics, data, starts=0)
    with pytest.raises(ValueError, match="margin"):
        multistart_least_squares(physics, data, margin=0.5)
    with pytest.raises(ValueError, match="parameter 'tau': no finite search box"):
        multistart_least_squares(physics, data, bounds={"tau": (0.0, np.inf)})
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['k'\]"):
        prior_box(physics, bounds={"k": (0.0, 1.0)})
    with pytest.raises(ValueError, match="coverage"):
        prior_box(physics, coverage=1.0)
    unbounded = PhysicsModel(
        _decay,
        {"A": Uniform(1.0, 2.0), "tau": Custom(lambda name, **kw: None, mean=np.inf)},
        inputs=["t"],
    )
    with pytest.raises(ValueError, match="parameter 'tau': no finite search box"):
        multistart_least_squares(unbounded, data)
