"""Multi-output calibration through emulators: one design, one simulator run for all
outputs, one GP per output whose covariance enters that output's likelihood
(kohpymc.multi_output.emulator, docs/multi-output.md)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from kohpymc import CalibrationData, StudyConfigError, Uniform
from kohpymc.emulator import run_design, space_filling_design
from kohpymc.multi_output import MultiOutputData, MultiOutputPhysics, calibrate_outputs
from kohpymc.multi_output.emulator import (
    emulate_outputs,
    emulated_outputs,
    output_design_box,
)

_PRIORS = {"a": Uniform(0.5, 3.0), "k": Uniform(0.2, 2.0)}
_TRUTH = {"a": 1.7, "k": 0.8}
_NOISE = 0.05
#: the outputs' own rows: level on a grid of [0, 3], rate between its points
_X = {"level": np.linspace(0.0, 3.0, 10), "rate": np.linspace(0.15, 2.85, 10)}
_SAMPLING = {"draws": 1000, "tune": 1000, "chains": 2, "random_seed": 1}


def _two(inputs, params):
    """A decay and its rate: two smooth outputs of one (a, k)."""
    e = np.exp(-params["k"] * inputs["x"])
    return {"level": params["a"] * e, "rate": params["a"] * params["k"] * e}


class _Counted:
    """``_two`` counting its calls and rows."""

    def __init__(self) -> None:
        self.calls = self.rows = 0

    def __call__(self, inputs, params):
        self.calls += 1
        self.rows += len(np.atleast_1d(inputs["x"]))
        return _two(inputs, params)


def _physics(function=_two):
    return MultiOutputPhysics(function, _PRIORS, ["x"], ["level", "rate"], name="two")


def _data(seed=1):
    rng = np.random.default_rng(seed)
    parts = {}
    for k, x in _X.items():
        y = _two({"x": x}, _TRUTH)[k] + rng.normal(0.0, _NOISE, x.size)
        parts[k] = CalibrationData({"x": x}, y, noise_sd=_NOISE)
    return MultiOutputData(parts)


def _posterior(cal):
    post = cal.posterior
    return {k: (float(post[k].mean()), float(post[k].std())) for k in _PRIORS}


# ------------------------------------------------------------------------ the runs


def test_one_simulator_call_per_run_gives_every_output_and_the_cache_keeps_them(tmp_path):
    counted = _Counted()
    physics = _physics(counted)
    design = space_filling_design(output_design_box(physics, _data()), 8, seed=3)
    runs = run_design(physics, design, cache=tmp_path, simulator_label="v1")
    assert counted.calls == 8 and runs.simulated == 8  # one call per θ, not one per output
    for k in physics.outputs:
        expected = [_two({"x": r.x}, {"a": r.a, "k": r.k})[k] for r in design.itertuples()]
        np.testing.assert_allclose(runs.output(k).y, expected, rtol=1e-12)
        assert list(runs.output(k).points.columns) == ["x", "a", "k", "output"]
    again = run_design(physics, design, cache=tmp_path, simulator_label="v1")
    assert counted.calls == 8 and (again.simulated, again.cached) == (0, 8)
    pd.testing.assert_frame_equal(again.points, runs.points)
    with pytest.raises(ValueError, match=r"\.output\(name\)"):
        _ = runs.y
    with pytest.raises(KeyError, match="'strain'"):
        runs.output("strain")
    # the simulator with a third output (same name and label) runs again: the cached
    # points lack that output; they then hold all three
    more = run_design(_physics_with(counted, 3), design, cache=tmp_path, simulator_label="v1")
    assert more.simulated == 8 and counted.calls == 16
    np.testing.assert_allclose(more.output("twice").y, 2 * runs.output("level").y)
    assert run_design(physics, design, cache=tmp_path, simulator_label="v1").simulated == 0


def _physics_with(counted, n_outputs):
    """``_two`` plus ``n_outputs - 2`` more outputs, named like ``_physics``."""

    def three(inputs, params):
        out = counted(inputs, params)
        return {**out, "twice": 2.0 * out["level"]}

    three.__name__ = "two"
    names = ["level", "rate", "twice"][:n_outputs]
    return MultiOutputPhysics(three, _PRIORS, ["x"], names, name="two")


def test_evaluating_every_output_runs_the_function_once():
    counted = _Counted()
    out = _physics(counted).evaluate({"x": [0.0, 1.0]}, {"a": 2.0, "k": 1.0})
    assert counted.calls == 1
    np.testing.assert_allclose(out["rate"], [2.0, 2.0 * np.exp(-1.0)])


# ------------------------------------------------------------------ the likelihood


def test_each_outputs_likelihood_gets_its_own_emulators_covariance():
    """M0 on both outputs: log p(y) is the sum over outputs of
    N(y_k | η̂_k(θ), Σ_η,k(θ) + σ² I), computed here from the GPs' numpy predictions."""
    from kohpymc.multi_output.model import compose_multi_output_model

    data = _data()
    emulators = emulate_outputs(_physics(), data, runs=12, seed=2)  # poor: Σ_η matters
    built = compose_multi_output_model(emulated_outputs(_physics(), emulators), data)
    model = built.model
    theta = {"a": 1.6, "k": 0.85}
    point = model.initial_point()
    point["a_interval__"] = np.log((1.6 - 0.5) / (3.0 - 1.6))
    point["k_interval__"] = np.log((0.85 - 0.2) / (2.0 - 0.85))
    observed = [model[f"{k}::y"] for k in data.outputs]
    logp = model.compile_fn(model.logp(vars=observed, sum=True), on_unused_input="ignore")
    expected = 0.0
    for k, em in emulators.items():
        x = _X[k]
        mean, _ = em.predict({"x": x}, theta)
        cov = _numpy_covariance(em, x, theta) + _NOISE**2 * np.eye(x.size)
        expected += stats.multivariate_normal(mean, cov).logpdf(data[k].y)
        assert np.sqrt(np.diag(cov)).max() > 2 * _NOISE  # the emulator's part dominates
    np.testing.assert_allclose(logp(point), expected, rtol=1e-6)


def _numpy_covariance(em, x, theta):
    """The GP's predictive covariance between rows at one θ, from its numpy kernel."""
    from kohpymc.emulator.gp import _kernel_numpy

    h = em.hyper
    Z = np.column_stack([x, np.full(x.size, theta["a"]), np.full(x.size, theta["k"])])
    U = (em._transform(Z) - em.lower) / em.width
    prior, _ = _kernel_numpy(em.kernel, U, U, h.lengthscales, h.amplitude)
    cross, _ = _kernel_numpy(em.kernel, U, em.U, h.lengthscales, h.amplitude)
    V = em._chol_inv @ cross.T
    return em.y_sd**2 * (prior - V.T @ V + h.nugget * np.eye(x.size))


# --------------------------------------------------------------- the posterior


@pytest.fixture(scope="module")
def direct_posterior():
    return _posterior(calibrate_outputs(_physics(), _data(), **_SAMPLING))


def test_a_near_exact_emulator_gives_the_direct_joint_posterior(direct_posterior):
    emulators = emulate_outputs(_physics(), _data(), runs=150, kernel="se", seed=1)
    cal = calibrate_outputs(emulated_outputs(_physics(), emulators), _data(), **_SAMPLING)
    emulated = _posterior(cal)
    for name, (mean, sd) in direct_posterior.items():
        assert abs(emulated[name][0] - mean) < 0.1 * sd, (name, emulated[name], mean, sd)
        assert 0.85 < emulated[name][1] / sd < 1.15, (name, emulated[name], sd)
