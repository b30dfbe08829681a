"""The emulator scored at a posterior mean (kohpymc.emulator.posterior_check)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import least_squares

import kohpymc as kp
from kohpymc.emulator import EmulatorWarning, emulate
from kohpymc.emulator.posterior_check import check_at_posterior

_NOISE = 0.02


def _decay(inputs, params):
    return params["A"] * np.exp(-params["k"] * np.asarray(inputs["t"], float))


def _nan_above(inputs, params):
    """The decay model, undefined (NaN) for k > 2.5: a solver failing in part of the box."""
    out = _decay(inputs, params)
    return out * np.nan if params["k"] > 2.5 else out


def _setup(function=_decay):
    physics = kp.PhysicsModel(
        function, {"A": kp.Uniform(0.5, 2.0), "k": kp.Uniform(0.1, 3.0)}, inputs=["t"],
        name="decay", on_nonfinite="reject",
    )  # fmt: skip
    t = np.linspace(0.0, 3.0, 40)
    rng = np.random.default_rng(3)
    y = _decay({"t": t}, {"A": 1.2, "k": 0.8}) + rng.normal(0.0, _NOISE, t.size)
    return physics, kp.CalibrationData(pd.DataFrame({"t": t}), y, noise_sd=_NOISE)


def _least_squares(predict, y):
    return least_squares(lambda th: predict({"A": th[0], "k": th[1]}) - y, [1.0, 1.0])


@pytest.mark.parametrize("runs", [12, 40])
def test_the_bias_matches_least_squares_through_emulator_and_simulator(runs):
    """Dense reference: the least-squares θ through the emulator's mean minus that through
    the simulator, in the simulator's linearised posterior sds, at the emulator's θ̂
    (measured: 40 runs -0.465/-0.221 against -0.456/-0.213; 12 runs +11.1/+4.07 against
    +9.89/+4.19, where one linear step is off by ~10 %)."""
    physics, data = _setup()
    t, y = data.inputs["t"], data.y
    em = emulate(physics, data, runs=runs, seed=1)
    through_em = _least_squares(lambda th: em.predict({"t": t}, th)[0], y)
    through_sim = _least_squares(lambda th: _decay({"t": t}, th), y)
    J = through_sim.jac
    sd = _NOISE * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    expected = (through_em.x - through_sim.x) / sd
    mean = {"A": through_em.x[0], "k": through_em.x[1]}
    check = check_at_posterior(em, data, mean, {"A": sd[0], "k": sd[1]})
    got = np.array([check.shift["A"], check.shift["k"]])
    np.testing.assert_allclose(got, expected, rtol=0.15, atol=0.05)
    assert check.fit == bool(np.all(np.abs(got) <= 0.25))
    if not check.fit:
        assert "biases A" in check.problems[-1] and "of that posterior's sds" in check.problems[-1]


def test_a_posterior_where_the_emulator_has_no_runs_is_flagged_and_cached(tmp_path):
    """The emulator's design covers k ∈ [0.1, 1.0] only; a posterior at k = 2 (outside)
    is flagged: the emulator extrapolates there, and its error biases k by tens of sds
    (its bands are wide enough to cover that error: the bias is what flags it).  The
    simulator's run there goes to the cache (a second check runs nothing)."""
    physics, data = _setup()
    em = emulate(physics, data, runs=40, seed=1, bounds={"k": (0.1, 1.0)})
    inside = check_at_posterior(em, data, {"A": 1.2, "k": 0.8}, {"A": 0.02, "k": 0.02})
    outside = check_at_posterior(
        em, data, {"A": 1.2, "k": 2.0}, {"A": 0.02, "k": 0.05}, label="M4's posterior",
        cache=tmp_path,
    )  # fmt: skip
    assert outside.rmse > 10 * inside.rmse
    assert abs(outside.shift["k"]) > 10 * abs(inside.shift["k"]) and abs(outside.shift["k"]) > 5
    assert not outside.fit and "at the mean of M4's posterior (A=1.2, k=2)" in outside.problems[0]
    cached = sorted(tmp_path.iterdir())
    assert cached
    check_at_posterior(em, data, {"A": 1.2, "k": 2.0}, {"A": 0.02, "k": 0.05}, cache=tmp_path)
    assert sorted(tmp_path.iterdir()) == cached


def test_a_simulator_failing_at_the_posterior_mean_is_a_problem_not_an_error():
    physics, data = _setup(_nan_above)
    with pytest.warns(EmulatorWarning, match="failed where k in"):
        em = emulate(physics, data, runs=30, seed=1)
    check = check_at_posterior(em, data, {"A": 1.2, "k": 2.8}, {"A": 0.1, "k": 0.1})
    assert not check.fit
    assert check.problems[0].startswith("the simulator failed at the mean of the posterior")
    assert "on 40 of 40 calibration rows (first: NonFiniteOutputError" in check.problems[0]


def test_an_exact_physics_model_has_no_posterior_problems():
    physics, data = _setup()
    assert physics.posterior_problems(data, {"A": 1.2, "k": 0.8}, {"A": 0.1, "k": 0.1}) == []


def test_an_unknown_noise_sd_moved_by_the_emulator_is_flagged():
    """Noise sd unknown: a 5-run emulator (sd 1.3 at the rows against noise 0.02) moves
    the noise sd's best fit by -0.9 of its sds (scored against the simulator's own
    residuals at the posterior mean), a 60-run one by -0.01.  With the noise sd given,
    nothing is judged."""
    physics, data = _setup()
    unknown = kp.CalibrationData(data.inputs, data.y)
    mean, sd = {"A": 1.2, "k": 0.8}, {"A": 0.05, "k": 0.05}
    poor = check_at_posterior(emulate(physics, unknown, runs=5, seed=1), unknown, mean, sd)
    good = check_at_posterior(emulate(physics, unknown, runs=60, seed=1), unknown, mean, sd)
    known = check_at_posterior(emulate(physics, data, runs=5, seed=1), data, mean, sd)
    assert poor.noise_shift < -0.5 and any("noise sd's best fit" in p for p in poor.problems)
    assert abs(good.noise_shift) <= 0.5 and not any("noise sd" in p for p in good.problems)
    assert known.noise_shift is None
