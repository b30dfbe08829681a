"""Term selection on linearised residuals: finds hidden effects, stays quiet on the null."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.optimize import least_squares

from kohpymc.candidates import CandidateTerm, candidate_library
from kohpymc.data import CalibrationData
from kohpymc.discovery import augmented_physics, disagreement_regions, discover, select_terms
from kohpymc.discovery.drift import physics_terms
from kohpymc.physics import PhysicsModel
from kohpymc.priors import Uniform

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


def _drag_physics():
    """Distance fallen from rest without drag, d = g t² / 2; the mass m is recorded."""
    return PhysicsModel(
        lambda x, p: 0.5 * p["g"] * x["t"] ** 2,
        {"g": Uniform(5.0, 15.0)},
        ["t", "m"],
        jacobian=lambda x, p: np.c_[0.5 * x["t"] ** 2],
        name="free fall",
    )


def _drag_data(seed: int, hidden: bool = True, known: bool = False):
    """Linear drag b v: d = g/k t - g/k² (1 - exp(-k t)), k = b/m (≈ g t²/2 - g k t³/6)."""
    rng = np.random.default_rng(seed)

    def make(t, m, sd=0.05):
        k = 0.5 / m
        if hidden:
            d = 9.81 / k * t - 9.81 / k**2 * (1 - np.exp(-k * t))
        else:
            d = 0.5 * 9.81 * t**2
        H = rng.uniform(20.0, 80.0, t.size)  # humidity: irrelevant
        y = d + rng.normal(0.0, sd, t.size)
        return CalibrationData({"t": t, "m": m, "H": H}, y, noise_sd=sd if known else None)

    cal = make(np.tile(np.linspace(0.2, 2.0, 10), 4), np.repeat([1.0, 2.0, 4.0, 8.0], 10))
    val = make(np.tile(np.linspace(2.0, 3.0, 5), 3), np.repeat([1.5, 3.0, 6.0], 5))
    return cal, val


PROBLEMS["falling_drag"] = (_drag_physics, _drag_data, {"t", "m"}, 0.1)


def _least_squares_selection(physics, data, *, null_draws=99, noise_sd="data"):
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
    terms = candidate_library(data.inputs) + physics_terms(physics, theta, data.inputs)
    sel = select_terms(
        data.y - physics.evaluate(data.inputs, theta),
        physics.jacobian_matrix(data.inputs, theta),
        terms,
        inputs=data.inputs,
        noise_sd=data.noise_sd if noise_sd == "data" else noise_sd,
        null_draws=null_draws,
    )
    named = {i for n in sel.best if n != "1" for i in sel.terms[n].inputs}
    return sel, named


@pytest.mark.parametrize("problem", sorted(PROBLEMS))
def test_selection_names_exactly_the_inputs_of_the_hidden_effect(problem):
    make_physics, make_data, truth, _ = PROBLEMS[problem]
    sel, named = _least_squares_selection(make_physics(), make_data(7)[0])
    assert named == truth
    assert sel.significant and sel.probability_none < 1e-3


def test_drag_is_named_as_a_negative_power_of_the_mass_without_the_noise_sd():
    sel, named = _least_squares_selection(_drag_physics(), _drag_data(7)[0], null_draws=0)
    assert named == {"t", "m"}
    best = sel.terms[sel.best[0]]
    assert sel.best == ("t^3/m",) or (best.kind == "drift" and "1/m" in best.name), sel.best
    assert sel.subsets[0][1] > 0.5


def test_an_input_that_varies_little_is_not_named_for_an_effect_without_it():
    """A 1/t effect on a grid where T spans only 800-900 K (an unseen creep study).

    Every ``T^a/t`` fits about as well as ``1/t``; with one prior unit per term the 36
    terms on (T, t) outweighed the 10 on t, and one of them, better by chance, named T
    at 3 of 6 seeds (2 of 6 even after preferring the plainest of near ties).
    """
    grid = np.meshgrid([50.0, 80.0, 120.0], [800.0, 850.0, 900.0], [10.0, 50, 100, 200, 400])
    inputs = dict(zip(("s", "T", "t"), (np.ravel(g) for g in grid), strict=True))
    terms = candidate_library(inputs)
    named = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        r = 0.02 / inputs["t"] + rng.normal(0, 2e-4, inputs["t"].size)
        sel = select_terms(r, np.c_[inputs["t"]], terms, inputs=inputs, noise_sd=None,
                           null_draws=0)  # fmt: skip
        named.append(sel.inputs_of(sel.plainest()))
    assert named == [{"t"}] * 6


@pytest.mark.parametrize("problem", sorted(PROBLEMS))
def test_selection_is_quiet_on_data_from_the_model_itself(problem):
    make_physics, make_data, _, _ = PROBLEMS[problem]
    physics = make_physics()
    alarms = [
        s
        for s in range(5)
        if _least_squares_selection(physics, make_data(s, False)[0], null_draws=99)[0].significant
    ]
    assert len(alarms) <= 1, alarms


def test_bad_input():
    r = np.zeros(4)
    with pytest.raises(ValueError, match="too few data points"):
        select_terms(r, np.ones((4, 2)), np.ones((4, 1)), ["a"], noise_sd=1.0)
    with pytest.raises(ValueError, match="no candidate"):
        select_terms(r, np.ones((4, 1)), np.ones((4, 0)), [], noise_sd=1.0)
    with pytest.raises(ValueError, match="every candidate term was rejected"):
        select_terms(np.arange(5.0), np.ones((5, 1)), np.ones((5, 1)), ["c"], noise_sd=1.0)
    with pytest.raises(ValueError, match="false_alarm"):
        select_terms(np.arange(5.0), np.c_[np.arange(5.0)], np.ones((5, 1)), ["c"],
                     noise_sd=None, false_alarm=1.0)  # fmt: skip


# ------------------------------------------------------------------ the evidence itself


def _brute_force_log_bf(r, J, phi, g, noise_sd):
    """log B of "r = J θ + c φ" against "r = J θ" by quadrature on a grid.

    Priors as in :mod:`kohpymc.discovery.evidence`: θ flat, c | σ ~ N(0, g σ² / |φ̃|²)
    with φ̃ = φ minus its projection on J, σ known or p(σ) ∝ 1/σ.
    """
    from scipy.special import logsumexp
    from scipy.stats import norm

    phit = phi - J @ np.linalg.lstsq(J, phi, rcond=None)[0]
    theta = np.linspace(-4.0, 6.0, 121)
    c = np.linspace(-4.0, 4.0, 121)
    log_s = np.linspace(-3.0, 2.0, 101) if noise_sd is None else np.array([np.log(noise_sd)])
    T, C, S = np.meshgrid(theta, c, log_s, indexing="ij")
    sd = np.exp(S)
    mean = T[..., None] * J[:, 0] + C[..., None] * phi
    loglik = norm.logpdf(r, mean, sd[..., None]).sum(-1)
    prior_c = norm.logpdf(C, 0.0, np.sqrt(g) * sd / np.linalg.norm(phit))
    d = (theta[1] - theta[0]) * (c[1] - c[0]) * (log_s[1] - log_s[0] if log_s.size > 1 else 1)
    num = logsumexp(loglik + prior_c) + np.log(d)
    loglik0 = norm.logpdf(r, T[:, 0, :, None] * J[:, 0], sd[:, 0, :, None]).sum(-1)
    den = logsumexp(loglik0) + np.log(d / (c[1] - c[0]))
    return num - den


@pytest.mark.parametrize("noise_sd", [None, 0.6])
def test_bayes_factor_equals_a_brute_force_integral(noise_sd):
    """Closed form (σ known or integrated out) against quadrature over θ, c and log σ."""
    from kohpymc.discovery.search import build_design, explain

    x = np.array([0.0, 0.4, 0.9, 1.3, 2.0, 2.5])
    r = np.array([1.1, 0.7, 1.6, 2.3, 2.2, 3.9])
    J, phi = np.c_[np.ones(6)], x**2  # J spans the constant: no separate offset
    design = build_design(J, np.c_[phi], ["x^2"])
    assert design.u is None
    _, log_bf, _ = explain(design, r, noise_sd=noise_sd, max_terms=1, g=6.0)
    assert log_bf[("x^2",)] == pytest.approx(
        _brute_force_log_bf(r, J, phi, 6.0, noise_sd), abs=0.01
    )


def test_a_constant_offset_is_named_as_the_constant_not_as_x():
    rng = np.random.default_rng(4)
    x = np.linspace(1.0, 5.0, 30)
    J = np.c_[x]  # y = a x: the model cannot shift the level
    inputs = {"x": x, "z": rng.uniform(0, 1, 30)}
    r = 0.8 + rng.normal(0.0, 0.1, 30)  # an unmodelled offset
    sel = select_terms(r, J, candidate_library(inputs), inputs=inputs, noise_sd=None)
    assert sel.significant and sel.best == ("1",)
    assert sel.subsets[0][1] > 0.5


def _level_and_trend(seed, trend, T=8.0, n=15, sd=0.3):
    """The review's case: a level model y = a, data a + trend · t, n = 15, σ = 0.3."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, T, n)
    y = 1.0 + trend * t + rng.normal(0.0, sd, n)
    return {"t": t}, y - y.mean(), np.ones((n, 1))


def test_unknown_noise_still_detects_the_missing_trend():
    """σ integrated out: the review's trend (0.15 t) found in most of 12 data sets.

    Measured over 100 seeds: 0.86 with σ unknown, 0.99 with σ = 0.3 given (the code
    before this change: 0.00 as shipped, 0.36 with σ fitted, 0.77 with σ given).
    """
    hits = 0
    for seed in range(12):
        inputs, r, J = _level_and_trend(seed, 0.15)
        lib = candidate_library(inputs)
        hits += select_terms(r, J, lib, inputs=inputs, noise_sd=None, null_draws=99,
                             random_seed=seed).significant  # fmt: skip
    assert hits >= 7  # 0.58: 3 binomial sds (0.1) below the measured 0.86


def _false_alarms(replicates, false_alarm, null_draws, shapes=()):
    alarms = 0
    for seed in range(replicates):
        inputs, r, J = _level_and_trend(seed, 0.0)
        inputs["w"] = np.random.default_rng(1000 + seed).uniform(1.0, 2.0, r.size)
        lib = candidate_library(inputs, max_inputs=2, shapes=shapes)
        alarms += select_terms(r, J, lib, inputs=inputs, noise_sd=None, null_draws=null_draws,
                               false_alarm=false_alarm, random_seed=seed).significant  # fmt: skip
    return alarms


def test_false_alarm_rate_is_the_stated_rate():
    """60 null data sets at a stated rate of 0.2: 12 alarms expected, binomial sd 3.1."""
    alarms = _false_alarms(60, 0.2, 24)
    assert abs(alarms - 12) <= 9, alarms  # 3 binomial sds


def test_false_alarm_rate_with_borrowed_theta_is_the_stated_rate():
    """θ borrowed from a second output (rows from
    :func:`kohpymc.multi_output.discovery.borrowed_rows`): the searched output knows θ1 and
    θ2 only through θ1 + θ2, the other pins both.  60 null data sets (linear, σ unknown)
    at a stated 0.2: 12 alarms expected, binomial sd 3.1."""
    from kohpymc.multi_output.discovery import borrowed_rows

    alarms = 0
    t = np.linspace(0.5, 4.0, 16)
    s = np.linspace(0.0, 1.0, 10)
    J = np.c_[t, t]  # G_k = (θ1 + θ2) t
    J_other = np.c_[np.ones(10), s**2]  # G_j = θ1 + θ2 s²
    for seed in range(60):
        rng = np.random.default_rng(seed)
        delta = rng.normal(0, 0.2, 2)  # the joint fit's error: Δθ is re-fitted
        r = J @ delta + rng.normal(0, 0.3, t.size)
        r_other = J_other @ delta + rng.normal(0, 0.1, s.size)
        A, b = borrowed_rows([J_other], [r_other], [0.1], 0.3)
        inputs = {"t": t, "w": np.random.default_rng(1000 + seed).uniform(1.0, 2.0, t.size)}
        lib = candidate_library(inputs, max_inputs=2)
        sel = select_terms(r, J, lib, inputs=inputs, noise_sd=None, null_draws=24,
                           false_alarm=0.2, random_seed=seed, borrowed=(A, b))  # fmt: skip
        alarms += sel.significant
    assert abs(alarms - 12) <= 9, alarms  # 3 binomial sds (measured: 14; not borrowed: 13)


@pytest.mark.slow
def test_false_alarm_rate_at_one_percent():
    """400 null data sets at 0.01 (shaped terms too): 4 alarms expected, sd 2."""
    alarms = _false_alarms(400, 0.01, 299, ("saturation", "threshold", "decay"))
    assert alarms <= 4 + 3 * 2, alarms


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


def test_a_drifting_parameter_is_varied_inside_the_physics_function():
    physics = _resistor_physics()
    cal, _ = _resistor_data(0)
    terms = physics_terms(physics, {"R": 10.0}, cal.inputs, exponents=(1,), output=False)
    drift = next(t for t in terms if t.name == "R~T")
    assert drift.meaning == "R depends on T, linearly" and set(drift.inputs) == {"T", "I"}
    aug = augmented_physics(physics, [drift], [1.0], offset_sd=1.0, inputs=cal.inputs,
                            theta={"R": 10.0})  # fmt: skip
    assert aug.parameter_names == ("R", "c_1", "c_0")
    y = aug.evaluate(cal.inputs, {"R": 10.0, "c_1": 0.04, "c_0": 0.5})
    np.testing.assert_allclose(y, cal.inputs["I"] * (10.0 + 0.04 * cal.inputs["T"]) + 0.5)


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


# ------------------------------------------- no closed form: the GP fallback (ARD inputs)
# Hooke's law with two recorded inputs it ignores (time t, humidity H); the truth adds an
# effect of t that no candidate term has: a damped bump or a logistic step.


def _hooke_with_time():
    return PhysicsModel(
        lambda x, p: x["F"] / p["k"],
        {"k": Uniform(20.0, 500.0)},
        ["F", "t", "H"],
        jacobian=lambda x, p: np.c_[-x["F"] / p["k"] ** 2],
        name="Hooke",
    )


def _no_closed_form_data(seed: int, kind: str, sd: float = 0.01):
    """0.3 sin(3t) exp(-t) ("bump") or 0.2 / (1 + exp(-(t - 2.5)/0.15)) ("step"), t in 0-5 s.

    56 times; every fourth is a validation row (inside the calibration range: a GP does
    not extrapolate), σ unknown.
    """
    rng = np.random.default_rng(seed)

    def make(t):
        F = rng.uniform(1.0, 10.0, t.size)
        H = rng.uniform(30.0, 70.0, t.size)
        if kind == "bump":
            effect = 0.3 * np.sin(3 * t) * np.exp(-t)
        elif kind == "step":
            effect = 0.2 / (1 + np.exp(-(t - 2.5) / 0.15))
        else:
            effect = 0.0
        y = F / 100.0 + effect + rng.normal(0.0, sd, t.size)
        return CalibrationData({"F": F, "t": t, "H": H}, y)

    t = np.linspace(0.0, 5.0, 56)
    val = np.arange(t.size) % 4 == 2
    return make(t[~val]), make(t[val])


def _ls_theta(physics, data) -> dict[str, float]:
    """The one physics parameter by least squares (positive, below 1000)."""
    (name,) = physics.parameters
    fit = least_squares(
        lambda v: physics.evaluate(data.inputs, {name: v[0]}) - data.y,
        [physics.parameters[name].mean()],
        bounds=(0.1, 1e3),
    )
    return {name: float(fit.x[0])}


def _closed_form_check(physics, data):
    """check_closed_form on the least-squares residual and the most probable explanation."""
    from kohpymc.discovery.fallback import check_closed_form

    sel, _ = _least_squares_selection(physics, data, null_draws=0)
    theta = _ls_theta(physics, data)
    r = data.y - physics.evaluate(data.inputs, theta)
    best = next(s for s, _ in sel.subsets if s)
    cols = [sel.terms[n](data.inputs) for n in best if n != "1"]
    phi = np.column_stack(cols) if cols else np.zeros((data.n, 0))
    return check_closed_form(
        data.inputs, r, physics.jacobian_matrix(data.inputs, theta), phi,
        dict(sel.subsets)[best], noise_sd=data.noise_sd,
    )  # fmt: skip


@pytest.mark.parametrize(("kind", "seed"), [("bump", 0), ("bump", 1), ("step", 0), ("step", 2)])
def test_no_closed_form_falls_back_to_a_gp_over_exactly_the_right_input(kind, seed):
    """The closed form is rejected by K-fold CV inside the calibration data; ARD names t."""
    check = _closed_form_check(_hooke_with_time(), _no_closed_form_data(seed, kind)[0])
    assert check.rejected, check.to_dict()
    assert check.relevance.relevant == ["t"]  # F (in the physics) and H are irrelevant
    assert check.cv_rmse["gp"] < check.cv_rmse["closed_form"] < check.cv_rmse["physics"]


@pytest.mark.parametrize("problem", sorted(PROBLEMS))
def test_a_case_the_library_explains_does_not_fall_back(problem):
    """Spring F³, sensor transient, resistor I·T, drag t³/m: the closed form is kept."""
    make_physics, make_data, truth, _ = PROBLEMS[problem]
    for seed in (3, 7):
        check = _closed_form_check(make_physics(), make_data(seed)[0])
        assert not check.rejected, (seed, check.to_dict())
        assert set(check.relevance.relevant) == truth  # ARD agrees with the closed form
        assert check.cv_rmse["closed_form"] < 0.5 * check.cv_rmse["physics"]


def test_ard_relevance_is_quiet_on_data_from_the_model_itself():
    """The GP route's own false alarms (level 0.001, its default at threshold 0.01): 0/24."""
    from kohpymc.discovery.fallback import ard_relevance

    alarms = []
    for problem in sorted(PROBLEMS):
        make_physics, make_data, _, _ = PROBLEMS[problem]
        physics = make_physics()
        for seed in range(6):
            data = make_data(seed, False)[0]
            theta = _ls_theta(physics, data)
            rel = ard_relevance(
                data.inputs, data.y - physics.evaluate(data.inputs, theta),
                physics.jacobian_matrix(data.inputs, theta), level=0.001,
            )  # fmt: skip
            if rel.relevant:
                alarms.append((problem, seed, rel.relevant))
    assert not alarms, alarms


def test_kfold_check_uses_held_out_calibration_rows():
    """A term fitted to noise lowers the in-sample residual but not the held-out one."""
    from kohpymc.discovery.fallback import kfold_rmse

    rng = np.random.default_rng(5)
    x = np.linspace(0.0, 1.0, 30)
    r = rng.normal(0.0, 0.1, 30)
    wiggle = np.c_[np.ones(30), np.cos(40 * x), np.sin(40 * x), x**7]
    in_sample = np.sqrt(np.mean((r - wiggle @ np.linalg.lstsq(wiggle, r, rcond=None)[0]) ** 2))
    assert in_sample < np.std(r)
    assert kfold_rmse(r, wiggle) > kfold_rmse(r, np.c_[np.ones(30)])


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["bump", "step"])
def test_discover_without_a_closed_form_calibrates_a_gp_over_the_right_input(kind):
    """Full workflow: "depends on t; no closed form found", validation RMSE at least halved."""
    cal, val = _no_closed_form_data(0, kind)
    report = discover(_hooke_with_time(), cal, val, tolerance=0.03, draws=300, tune=300,
                      chains=2, random_seed=0)  # fmt: skip
    assert report.significant and report.inputs == ["t"]
    assert report.effect == "depends on t; no closed form found"
    assert report.fallback is not None and report.fallback["formulation"] == "gp"
    out = json.loads(json.dumps(report.to_dict()))  # the JSON report, as the CLI writes it
    assert out["closed_form_found"] is False and out["fallback"]["inputs"] == ["t"]
    before, after = report.validation["before"], report.validation["after"]
    assert after["rmse"] <= 0.5 * before["rmse"]
    assert after["mu_r"] > before["mu_r"]


def test_the_validation_data_never_choose_the_explanation():
    """Same calibration data, validation outputs replaced by nonsense: same choice.

    The terms, their posterior, the K-fold check and the inputs come from the
    calibration data alone; only the before/after scores see the validation data.
    """
    physics = _spring_physics()
    cal, val = _spring_data(3)
    nonsense = CalibrationData(val.inputs, val.y[::-1] + 5.0, noise_sd=val.noise_sd)
    kw = {"tolerance": 3e-3, "draws": 150, "tune": 150, "chains": 1, "random_seed": 3}
    a = discover(physics, cal, val, **kw).to_dict()
    b = discover(physics, cal, nonsense, **kw).to_dict()
    for key in ("significant", "effect", "inputs", "explanations", "closed_form_check"):
        assert a[key] == b[key], key
    assert a["closed_form_check"]["cv_improves"]  # the chosen term lowers held-out residuals
    assert a["validation"]["before"]["rmse"] != b["validation"]["before"]["rmse"]


# ----------------------------------------------------------------------------- units


def _reynolds_data(seed: int):
    """y = a v (inputs v, D, ρ, μ); the truth adds 2e-4 Re, Re = ρ v D / μ (four inputs)."""
    rng = np.random.default_rng(seed)
    n = 60
    x = {
        "v": rng.uniform(0.5, 3.0, n),  # m/s
        "D": rng.uniform(0.01, 0.05, n),  # m
        "rho": rng.uniform(800.0, 1200.0, n),  # kg/m^3
        "mu": rng.uniform(1e-3, 5e-3, n),  # Pa s
    }
    re = x["rho"] * x["v"] * x["D"] / x["mu"]
    y = 1.5 * x["v"] + 2e-4 * re + rng.normal(0.0, 0.01, n)
    return x, y


def test_units_offer_a_dimensionless_group_of_four_inputs():
    """Re = ρvD/μ is no monomial of at most three inputs; with units it is a π group."""
    from kohpymc.discovery.dimensions import coefficient_unit, pi_terms, read_units

    x, y = _reynolds_data(0)
    J = np.c_[x["v"]]
    given = {"v": "m/s", "D": "m", "rho": "kg/m^3", "mu": "Pa*s", "output": "N"}
    units = read_units(given, list(x))
    lib = candidate_library(x, exponents=(-1, 1, 2))
    pis, groups = pi_terms(x, units, (-1, 1, 2), taken={t.name for t in lib})
    assert groups == [{"v": 1, "D": 1, "rho": 1, "mu": -1}]
    assert [t.name for t in pis] == ["mu/(v*D*rho)", "v*D*rho/mu", "v^2*D^2*rho^2/mu^2"]
    r = y - 1.5 * x["v"]
    with_units = select_terms(r, J, lib + pis, inputs=x, noise_sd=None, null_draws=0)
    assert with_units.best == ("v*D*rho/mu",)
    term = with_units.terms["v*D*rho/mu"]
    assert term.meaning == "the dimensionless group v*D*rho/mu"
    assert coefficient_unit(term, given) == "N"  # output / 1
    without = select_terms(r, J, lib, inputs=x, noise_sd=None, null_draws=0)
    assert without.best != ("v*D*rho/mu",) and without.subsets[0][1] < with_units.subsets[0][1]


def test_coefficient_units_in_the_report():
    """Drag named as t³/m: c_1 in m·kg/s³ (m / (s³/kg)), the offset c_0 in m."""
    cal, val = _drag_data(3)
    report = discover(
        _drag_physics(), cal, val, tolerance=0.1, units={"t": "s", "m": "kg", "output": "m"},
        draws=150, tune=150, chains=1, random_seed=3,
    )  # fmt: skip
    out = report.to_dict()
    assert report.effect == "c * t^3/m + c_0"
    assert out["units"]["fitted"] == {"c_1": "m*kg/s^3", "c_0": "m"}
    assert out["explanations"][0]["coefficient_units"] == ["m*kg/s^3", "m"]
    drifts = {}
    for e in out["explanations"][1:]:
        named = [t for t in e["terms"] if t != "1"]
        drifts.update({n: u for n, u in zip(named, e.get("coefficient_units", []), strict=False)
                       if "~" in n})  # fmt: skip
    assert drifts, "no drift term among the explanations"
    for name, unit in drifts.items():  # g's unit is not declared: [g] per unit of g(x)
        assert unit.startswith("[g]"), (name, unit)
    if "g~t" in drifts:
        assert drifts["g~t"] == "[g]/s"
    with pytest.raises(ValueError, match=r"units\.m: unknown unit 'kilogram'"):
        discover(_drag_physics(), cal, val, tolerance=0.1, units={"m": "kilogram"})


def test_a_constant_offset_passes_the_kfold_check():
    """y = a x cannot shift its level: the offset alone lowers the held-out residual."""
    from kohpymc.discovery.fallback import check_closed_form

    rng = np.random.default_rng(4)
    x = np.linspace(1.0, 5.0, 30)
    inputs = {"x": x, "z": rng.uniform(0, 1, 30)}
    r = 0.8 + rng.normal(0.0, 0.1, 30)
    check = check_closed_form(inputs, r, np.c_[x], np.zeros((30, 0)), 0.9)
    assert not check.rejected and check.to_dict()["cv_improves"]
    assert check.cv_rmse["closed_form"] < 0.5 * check.cv_rmse["physics"]


def test_an_improbable_but_right_closed_form_is_kept():
    """Benchmark case T⁴ at 5 % noise: the best closed form has P < 0.1, but a GP over T
    predicts held-out rows only ~1 % better — no fallback (0/64 benchmark sets fall back)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from benchmarks.discovery import _bounds, _data, _fit
    from benchmarks.discovery_cases import CASES
    from kohpymc.discovery.fallback import check_closed_form

    case = next(c for c in CASES if c.name == "radiation T^4")
    for seed in (0, 1):
        xc, yc, _, _, _ = _data(case, seed, 0.05)
        physics = case.physics()
        theta = _fit(physics, xc, yc, physics.prior_mean(), _bounds(physics))
        r, J = yc - physics.evaluate(xc, theta), physics.jacobian_matrix(xc, theta)
        lib = candidate_library(xc) + physics_terms(physics, theta, xc)
        sel = select_terms(r, J, lib, inputs=xc, noise_sd=None, null_draws=0)
        best = next(s for s, _ in sel.subsets if s)
        phi = np.column_stack([sel.terms[n](xc) for n in best if n != "1"])
        check = check_closed_form(xc, r, J, phi, dict(sel.subsets)[best], level=0.01)
        assert dict(sel.subsets)[best] < 0.1  # the case this test is about
        assert not check.rejected, check.to_dict()
        assert check.relevance.relevant == ["T"]
