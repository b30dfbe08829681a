"""The check at the data of a functional (principal-component) emulator
(kohpymc.emulator.functional_at_data, through kohpymc.emulator.checking.check_at_data) and
the warning of a functional study from it (kohpymc.emulator.functional_study)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import least_squares

from kohpymc import PhysicsModel, Uniform
from kohpymc.emulator import (
    EmulatorWarning,
    FunctionalEmulator,
    run_curves,
    space_filling_design,
)
from kohpymc.emulator.checking import check_at_data
from kohpymc.examples import decay

_GRID = {"t": list(decay.CALIBRATION_TIMES)}
_BOX = {"A": (0.2, 6.0), "k": (0.05, 3.0)}
#: around the decay example's truth A = 2, k = 0.7: where sequential rounds put curves
_NEAR = {"A": (1.85, 2.15), "k": (0.62, 0.78)}


def _data():
    return decay.generate_data(seed=1)


def _physics():
    """The decay model with uniform priors over :data:`_BOX` (the study's design box)."""
    priors = {k: Uniform(lo, hi) for k, (lo, hi) in _BOX.items()}
    return PhysicsModel(decay.exponential_decay, priors, inputs=["t"], name="exponential_decay")


def _emulator(over_box: int, near: int) -> FunctionalEmulator:
    """Curves at ``over_box`` θ over the box and ``near`` θ around the data's fit."""
    physics = _physics()
    parts = [space_filling_design(_BOX, over_box, seed=0)]
    if near:
        parts.append(space_filling_design(_NEAR, near, seed=0))
    design = pd.concat(parts, ignore_index=True)
    return FunctionalEmulator(run_curves(physics, design, _GRID), physics, box=_BOX, restarts=1)


def _simulator_fit(data):
    """The simulator's own least-squares θ and its linearised sds (noise = rms residual)."""

    def residual(theta):
        return decay.exponential_decay(data.inputs, {"A": theta[0], "k": theta[1]}) - data.y

    fit = least_squares(residual, [1.0, 1.0])
    noise = np.sqrt(np.mean(fit.fun**2))
    return fit.x, noise * np.sqrt(np.diag(np.linalg.inv(fit.jac.T @ fit.jac)))


def test_an_emulator_poor_over_the_box_but_good_at_the_data_passes_there():
    """6 curves over the box and 12 around the data (as after sequential rounds): over
    the box its held-out RMSE is 0.21 of the outputs' sd (a problem), at the data its
    best fit is the simulator's own least-squares θ (closed-form decay, scipy) within
    0.05 sd, the simulator there is A e^{-kt} at that θ, and its error (rms 1.6e-4) is
    far below the misfit (0.027): the check passes."""
    em, data = _emulator(6, 12), _data()
    held = em.held_out_check(
        run_curves(em.physics, space_filling_design(_BOX, 8, method="sobol", seed=1), _GRID)
    )
    assert any("RMSE" in p for p in held.problems), held.problems
    with warnings.catch_warnings():
        warnings.simplefilter("error", EmulatorWarning)
        check = check_at_data(em, data)
    assert check.fit and check.kind == "at the calibration data", check.problems
    best, sds = _simulator_fit(data)
    point = np.array([check.point["A"], check.point["k"]])
    assert np.all(np.abs(point - best) < 0.05 * sds), (point, best, sds)
    np.testing.assert_allclose(
        check.simulated, decay.exponential_decay(data.inputs, check.point), rtol=1e-12
    )
    assert check.rmse < 0.01 * check.misfit and check.coverage == 1.0
    assert max(abs(v) for v in check.shift.values()) < 0.05
    assert max(check.widening.values()) < 1.1


def test_a_poor_functional_emulator_fails_at_the_data_and_says_why():
    """6 curves over the whole box (none near the data): its error at the best fit moves
    the least-squares θ by sds, and the warning names it and the curves."""
    em, data = _emulator(6, 0), _data()
    with pytest.warns(EmulatorWarning, match=r"exponential_decay' \(6 curves\) is not fit") as seen:
        check = check_at_data(em, data)
    assert not check.fit
    assert any("moves the least-squares θ" in p for p in check.problems), check.problems
    assert "moves the least-squares θ" in str(seen[0].message)
    best, sds = _simulator_fit(data)
    moved = (np.array([check.point["A"], check.point["k"]]) - best) / sds
    assert np.max(np.abs(moved)) > 0.25, moved  # the emulator's best fit is really off


@pytest.mark.parametrize("curves", [14, 20])
def test_the_predicted_move_of_theta_is_the_simulators_own_least_squares(curves):
    """14 and 20 curves over the box, none near the data: the check predicts (linearised)
    how far the simulator's least-squares θ lies from the emulator's best fit; scipy's
    fit of the closed-form decay gives it (measured: k 0.84 predicted against 0.78, and
    1.50 against 1.40 sds).  Both move θ by more than 0.25 sds: the check fails."""
    em, data = _emulator(curves, 0), _data()
    check = check_at_data(em, data, warn=False)
    best, sds = _simulator_fit(data)
    actual = (best - np.array([check.point["A"], check.point["k"]])) / sds
    predicted = np.array([check.shift["A"], check.shift["k"]])
    assert np.all(np.abs(predicted - actual) < 0.15 + 0.2 * np.abs(actual)), (predicted, actual)
    assert not check.fit and np.max(np.abs(actual)) > 0.5


def test_the_check_leaves_out_curves_run_at_the_best_fit():
    """A curve run at θ̂ itself would only be repeated by the emulator: the prediction
    there is that of the other curves (the same as an emulator without it, whose weight
    GPs keep the hyperparameters)."""
    from kohpymc.emulator.at_data import EmulatorsAtData

    em, data = _emulator(6, 0), _data()
    theta = dict(zip(("A", "k"), em.runs.design[["A", "k"]].iloc[2], strict=True))
    target = EmulatorsAtData.of(em, data)
    mean, _ = target.predicted_at("output", theta)
    own, _ = em.predict(data.inputs, theta)
    simulated = decay.exponential_decay(data.inputs, theta)
    assert np.max(np.abs(own - simulated)) < 0.2 * np.max(np.abs(mean - simulated))
    drop = np.arange(em.n_runs) == 2
    by_hand = em.predict(data.inputs, theta, without=drop)[0]
    np.testing.assert_allclose(mean, by_hand)


# ---------------------------------------------------------------- in a functional study


def _near_rounds(settings, physics, calibration, emulator, folder, **kwargs):
    """Stands in for the sequential rounds: 12 curves around the data's fit."""
    design = space_filling_design(_NEAR, 12, seed=0)
    return emulator.refitted(run_curves(physics, design, _GRID, cache=folder / "runs"))


def _study(tmp_path, runs, sequential=0):
    from kohpymc.emulator.functional_study import study_functional_physics
    from kohpymc.emulator.study import EmulatorSettings

    settings = EmulatorSettings(
        functional=("t",), runs=runs, sequential=sequential, log_output=False, seed=1
    )
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        physics = study_functional_physics(settings, _physics(), _data(), tmp_path)
    warned = [str(w.message) for w in seen if issubclass(w.category, EmulatorWarning)]
    folder = tmp_path / "emulator"
    held = json.loads((folder / "check.json").read_text())
    return physics.emulator, warned, held, json.loads((folder / "check_at_data.json").read_text())


def test_a_study_does_not_warn_when_only_the_box_wide_check_fails(tmp_path, monkeypatch):
    """8 first curves plus 12 near the data: the held-out check over the prior box fails
    (written to check.json), the check at the data passes: no warning.  A rerun restores
    the rounds' emulator from the cache and reads the recorded check."""
    import kohpymc.emulator.functional_study as functional_study

    monkeypatch.setattr(functional_study, "run_rounds", _near_rounds)
    em, warned, held, at_data = _study(tmp_path, runs=8, sequential=1)
    assert em.n_runs == 8 + 12 and held["problems"], held
    assert at_data["problems"] == [], at_data
    assert warned == []
    assert at_data["rmse"] < 0.5 * at_data["misfit"] and set(at_data["point"]) == {"A", "k"}

    def no_check(*args, **kwargs):
        raise AssertionError("checked again")

    monkeypatch.setattr(functional_study, "write_check_at_data", no_check)
    again, warned, _, _ = _study(tmp_path, runs=8, sequential=1)
    assert warned == [] and again.runs.simulated == 0 and again.n_runs == 8 + 12


def test_a_study_warns_from_the_check_at_the_data_naming_the_box_wide_one(tmp_path, monkeypatch):
    """4 curves: one warning, from the check at the data, naming its problems and the
    held-out ones; a rerun restoring the rounds' emulator warns again from the record."""
    import kohpymc.emulator.functional_study as functional_study

    monkeypatch.setattr(functional_study, "run_rounds", lambda *args, **kwargs: args[3])
    _, warned, held, at_data = _study(tmp_path, runs=4, sequential=1)
    assert held["problems"] and at_data["problems"]
    assert len(warned) == 1, warned
    message = warned[0]
    assert "(4 curves) is not fit for this calibration: at {A=" in message
    assert at_data["problems"][0] in message
    assert "; over its design, held-out" in message
    assert message.endswith("add curves ([emulator] runs or sequential rounds)")
    _, again, _, _ = _study(tmp_path, runs=4, sequential=1)
    assert len(again) == 1 and "recorded in check_at_data.json" in again[0], again


def _fragile_decay(inputs, params):
    if params["k"] < 1.0:  # the data's k (0.7) is where this solver fails
        raise RuntimeError("step size too small")
    return decay.exponential_decay(inputs, params)


def test_curves_failing_at_the_best_fit_are_an_error_saying_where_and_what_to_do(tmp_path):
    """As for scalar runs: the error names θ̂, the failed curves, the design's failures and
    what to do (before: "check_at_data: 1 curve(s) of 'fragile' failed at the best fit")."""
    priors = {k: Uniform(lo, hi) for k, (lo, hi) in _BOX.items()}
    physics = PhysicsModel(_fragile_decay, priors, inputs=["t"], name="fragile")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the design's own failures are warned about
        runs = run_curves(physics, space_filling_design(_BOX, 24, seed=0), _GRID)
        em = FunctionalEmulator(runs, physics, box=_BOX, restarts=1)
    assert 0 < len(runs.failed) < 24
    pattern = (
        r"failed at the emulator's best fit to the data \{A=.*, k=0\.\d+\} on 1 of 1 curves "
        rf"\(first: .*step size too small[^)]*\); {len(runs.failed)} of the emulator's 24 "
        r"design runs failed too\..*narrow the parameters' prior box"
    )
    with pytest.raises(RuntimeError, match=pattern):
        check_at_data(em, _data(), cache=tmp_path, warn=False)
