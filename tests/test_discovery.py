"""Term selection on linearised residuals: finds hidden effects, stays quiet on the null."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from kohpymc.candidates import CandidateTerm, candidate_library, design_matrix
from kohpymc.data import CalibrationData
from kohpymc.discovery import augmented_physics, disagreement_regions, discover, select_terms
from kohpymc.examples import beam
from kohpymc.physics import PhysicsModel
from kohpymc.priors import Uniform


def _beam_selection(seed: int, *, hidden: bool):
    rng = np.random.default_rng(seed)
    data = beam.generate_data((2.5, 3.0), seed=seed)
    x, P = data.inputs["x"], data.inputs["P"]
    physics = beam.physics_model()
    y = (
        data.y
        if hidden
        else beam.euler_bernoulli(data.inputs, {"E": 200.0})
        + rng.normal(0.0, data.noise_sd, data.n)
    )
    fit = least_squares(lambda e: physics.evaluate(data.inputs, {"E": e[0]}) - y, [150.0])
    e_hat = float(fit.x[0])
    resid = y - physics.evaluate(data.inputs, {"E": e_hat})
    J = physics.jacobian_matrix(data.inputs, {"E": e_hat})
    inputs = {"x": x, "P": P, "z": rng.uniform(0, 1, data.n)}  # z: irrelevant
    terms = candidate_library(inputs)
    sel = select_terms(
        resid,
        J,
        design_matrix(terms, inputs),
        [t.name for t in terms],
        noise_sd=data.noise_sd,
        parameter_sd=[250 / np.sqrt(12)],
    )
    named = {i for t in terms if t.name in sel.best for i in t.inputs}
    return sel, named


def test_beam_shear_term_depends_on_x_and_p_only():
    sel, named = _beam_selection(2026, hidden=True)
    assert named == {"x", "P"}
    assert sel.probability_none < 1e-6


def test_null_data_gives_at_most_one_false_alarm_in_ten_seeds():
    alarms = sum(bool(_beam_selection(s, hidden=False)[0].best) for s in range(10))
    assert alarms <= 1


def test_bad_input():
    r = np.zeros(3)
    with pytest.raises(ValueError, match="too few data points"):
        select_terms(r, np.ones((3, 2)), np.ones((3, 1)), ["a"], noise_sd=1.0, parameter_sd=[1, 1])
    with pytest.raises(ValueError, match="no candidate"):
        select_terms(r, np.ones((3, 1)), np.ones((3, 0)), [], noise_sd=1.0, parameter_sd=[1])
    with pytest.raises(ValueError, match="every candidate term was rejected"):
        select_terms(
            np.arange(5.0), np.ones((5, 1)), np.ones((5, 1)), ["c"], noise_sd=1.0, parameter_sd=[1]
        )


# --------------------------------------------------- other physics with a hidden effect
# Each problem: a physics model that ignores one recorded input (irrelevant by
# construction), data from a truth that adds an effect of a different kind, and the set
# of inputs that effect depends on.


def _spring_physics():
    """Hooke's law u = F / k; the temperature T is recorded but plays no role."""
    return PhysicsModel(
        lambda x, p: x["F"] / p["k"],
        {"k": Uniform(20.0, 500.0)},
        ["F", "T"],
        jacobian=lambda x, p: np.c_[-x["F"] / p["k"] ** 2],
        name="Hooke",
    )


def _spring_data(seed: int, hidden: bool = True):
    """Softening spring: the truth adds 1e-4 F³ (a higher power of one input)."""
    rng = np.random.default_rng(seed)

    def make(F):
        T = rng.uniform(15.0, 35.0, F.size)
        y = F / 100.0 + (1e-4 * F**3 if hidden else 0.0) + rng.normal(0.0, 1e-3, F.size)
        return CalibrationData({"F": F, "T": T}, y, noise_sd=1e-3)

    return make(np.linspace(0.5, 7.0, 30)), make(np.linspace(7.5, 10.0, 12))


def _sensor_physics():
    """Bridge output v = s L; time t and humidity H are recorded but play no role."""
    return PhysicsModel(
        lambda x, p: p["s"] * x["L"],
        {"s": Uniform(0.5, 2.0)},
        ["t", "L", "H"],
        jacobian=lambda x, p: np.c_[x["L"]],
        name="bridge",
    )


def _sensor_data(seed: int, hidden: bool = True):
    """Warm-up drift: the truth adds 0.8 exp(-t / 15 s) (an exponential transient)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0, 2.0)
    L = rng.choice([1.0, 2.0, 3.0, 4.0, 5.0], t.size)
    H = rng.uniform(30.0, 70.0, t.size)
    drift = 0.8 * np.exp(-t / 15.0) if hidden else 0.0
    y = 1.2 * L + drift + rng.normal(0.0, 0.05, t.size)
    data = CalibrationData({"t": t, "L": L, "H": H}, y, noise_sd=0.05)
    odd = np.arange(t.size) % 2 == 1  # interleaved in time, as in the paper
    return data.subset(~odd), data.subset(odd)


def _resistor_physics():
    """Ohm's law V = I R; temperature T and humidity H recorded; strict about its keys."""

    def ohm(x, p):
        if set(p) != {"R"}:
            raise KeyError(f"unexpected parameters {sorted(p)}")
        return x["I"] * p["R"]

    return PhysicsModel(
        ohm, {"R": Uniform(1.0, 100.0)}, ["I", "T", "H"], jacobian=lambda x, p: np.c_[x["I"]],
        name="Ohm",
    )  # fmt: skip


def _resistor_data(seed: int, hidden: bool = True):
    """Self-heating: R = 10 (1 + 0.004 (T - 20)), an interaction I·T; validated at 60 °C."""
    rng = np.random.default_rng(seed)

    def make(T):
        current = rng.uniform(0.1, 1.0, T.size)
        H = rng.uniform(30.0, 70.0, T.size)
        R = 10.0 * (1.0 + (0.004 * (T - 20.0) if hidden else 0.0))
        y = current * R + rng.normal(0.0, 0.01, T.size)
        return CalibrationData({"I": current, "T": T, "H": H}, y, noise_sd=0.01)

    return make(np.repeat([20.0, 30.0, 40.0], 10)), make(np.full(12, 60.0))


#: name -> (physics, data, true inputs of the hidden effect, tolerance ε)
PROBLEMS = {
    "spring_power": (_spring_physics, _spring_data, {"F"}, 3e-3),
    "sensor_transient": (_sensor_physics, _sensor_data, {"t"}, 0.1),
    "resistor_interaction": (_resistor_physics, _resistor_data, {"I", "T"}, 0.03),
}


def _least_squares_selection(physics, data):
    """select_terms on the residual of a least-squares fit (no sampling)."""
    (name,) = physics.parameters
    prior = physics.parameters[name]
    half = np.sqrt(3.0) * prior.sd()  # the priors here are uniform: mean ± √3 sd
    fit = least_squares(
        lambda v: physics.evaluate(data.inputs, {name: v[0]}) - data.y,
        [prior.mean()],
        bounds=(prior.mean() - half, prior.mean() + half),
    )
    theta = {name: float(fit.x[0])}
    terms = candidate_library(data.inputs)
    sel = select_terms(
        data.y - physics.evaluate(data.inputs, theta),
        physics.jacobian_matrix(data.inputs, theta),
        design_matrix(terms, data.inputs),
        [t.name for t in terms],
        noise_sd=data.noise_sd,
        parameter_sd=[prior.sd()],
    )
    return sel, {i for t in terms if t.name in sel.best for i in t.inputs}


@pytest.mark.parametrize("problem", sorted(PROBLEMS))
def test_selection_names_exactly_the_inputs_of_the_hidden_effect(problem):
    make_physics, make_data, truth, _ = PROBLEMS[problem]
    sel, named = _least_squares_selection(make_physics(), make_data(7)[0])
    assert named == truth
    assert sel.probability_none < 1e-3


@pytest.mark.parametrize("problem", sorted(PROBLEMS))
def test_selection_is_quiet_on_data_from_the_model_itself(problem):
    make_physics, make_data, _, _ = PROBLEMS[problem]
    physics = make_physics()
    alarms = [
        s for s in range(10) if _least_squares_selection(physics, make_data(s, False)[0])[0].best
    ]
    assert len(alarms) <= 1, alarms


def test_disagreement_regions_merge_adjacent_failing_bins():
    t = np.arange(0.0, 40.0)
    z = np.where(t < 10, 4.0, 0.0) + np.where(t >= 35, 4.0, 0.0)
    regions = disagreement_regions(
        t, lambda rows: bool(np.mean(z[rows] ** 2) > 1), input_name="t", source="calibration"
    )
    assert [(r["from"], r["to"]) for r in regions] == [(0.0, 9.0), (35.0, 39.0)]
    assert [r["rows"] for r in regions] == [10, 5]
    # equal values are never split between two bins
    x = np.repeat([1.0, 2.0, 3.0], 7)
    regions = disagreement_regions(
        x, lambda rows: bool(np.all(x[rows] == 2.0)), input_name="x", source="validation"
    )
    assert [(r["from"], r["to"], r["rows"]) for r in regions] == [(2.0, 2.0, 7)]


def test_augmented_model_calls_the_physics_with_its_own_parameters_only():
    physics = _resistor_physics()
    cal, _ = _resistor_data(0)
    heating = CandidateTerm("I*T", ("I", "T"), lambda d: d["I"] * d["T"])
    aug = augmented_physics(physics, [heating], [1.0])
    assert aug.parameter_names == ("R", "c_1")
    y = aug.evaluate(cal.inputs, {"R": 10.0, "c_1": 0.04})
    np.testing.assert_allclose(y, cal.inputs["I"] * (10.0 + 0.04 * cal.inputs["T"]))
    np.testing.assert_allclose(
        aug.jacobian_matrix(cal.inputs, {"R": 10.0, "c_1": 0.0}),
        np.c_[cal.inputs["I"], cal.inputs["I"] * cal.inputs["T"]],
    )


def test_discover_rejects_bad_input_before_sampling():
    physics = _spring_physics()
    cal, val = _spring_data(0)
    kw = {"tolerance": 3e-3, "draws": 10, "tune": 10, "chains": 1, "random_seed": 0}
    with pytest.raises(ValueError, match="candidate library is empty"):
        discover(physics, cal, val, candidates=[], **kw)
    shifted_log = {"log(F-2)": (["F"], lambda d: np.log(d["F"] - 2.0))}  # NaN below 2 N
    with pytest.raises(ValueError, match=r"calibration data: candidate term 'log\(F-2\)'"):
        discover(physics, cal, val, extra_terms=shifted_log, **kw)
    with pytest.raises(ValueError, match="too few data points.*3 rows"):
        discover(physics, cal.subset(np.arange(cal.n) < 3), val, **kw)

    def tabulated(x, p):  # a lookup table that ends at F = 7.2
        if np.max(x["F"]) > 7.2:
            raise ValueError("F outside the tabulated range 0-7.2 N")
        return x["F"] / p["k"]

    table = PhysicsModel(tabulated, {"k": Uniform(20.0, 500.0)}, ["F", "T"], name="table")
    with pytest.raises(ValueError, match="'table' fails on the validation inputs.*tabulated"):
        discover(table, cal, val, **kw)
    with pytest.raises(ValueError, match="tolerance"):
        discover(physics, cal, val, **{**kw, "tolerance": 0.0})


def _full_discovery(problem: str, seed: int, hidden: bool = True):
    make_physics, make_data, _, tolerance = PROBLEMS[problem]
    cal, val = make_data(seed, hidden)
    return discover(
        make_physics(), cal, val, tolerance=tolerance, draws=400, tune=400, chains=2,
        random_seed=seed,
    )  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("problem", sorted(PROBLEMS))
def test_discover_names_adds_and_closes_the_gap(problem):
    """Full workflow: named inputs exact, validation RMSE at least halves, μ_r rises."""
    truth = PROBLEMS[problem][2]
    report = _full_discovery(problem, seed=3)
    assert report.significant
    assert set(report.inputs) == truth
    for k, p in report.input_probability.items():
        assert (p > 0.99) if k in truth else (p < 0.5), (k, p)  # irrelevant: not named
    before, after = report.validation["before"], report.validation["after"]
    assert after["rmse"] <= 0.5 * before["rmse"]
    assert after["mu_r"] > before["mu_r"] + 3 * np.hypot(before["mu_r_mcse"], after["mu_r_mcse"])
    assert report.where and {w["input"] for w in report.where} <= truth
    assert report.key_input in truth


@pytest.mark.slow
def test_discover_on_data_from_the_model_itself_changes_nothing():
    """Null: 12 data sets (4 seeds x 3 models) from the models themselves, <= 1 alarm."""
    alarms = []
    for problem in sorted(PROBLEMS):
        for seed in range(4):
            report = _full_discovery(problem, seed, hidden=False)
            if report.significant:
                alarms.append((problem, seed, report.effect))
                continue
            assert report.effect is None and report.inputs == [] and report.where == []
            assert report.validation["after"] == report.validation["before"]
            assert report.parameters["after"] == report.parameters["before"]
            assert report.physics.name == PROBLEMS[problem][0]().name
    assert len(alarms) <= 1, alarms
