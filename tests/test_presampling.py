"""Before sampling: identifiability at the posterior mode, and the sampling-time estimate."""

import json
import time
import warnings

import numpy as np
import pytest

from kohpymc import CalibrationData, PhysicsModel, Uniform, calibrate
from kohpymc.identifiability import IdentifiabilityWarning
from kohpymc.presampling import SlowSamplingWarning, probe_steps, slow_reasons
from kohpymc.reparameterization import Coordinates, Reparameterization

SEED = 31


def _hinge():
    """y = a + c·max(x − t, 0): with t at its prior centre (15) beyond the data (x ≤ 10)
    neither c nor t changes the output; at the truth (t = 4) both do."""

    def hinge(i, p):
        return p["a"] + p["c"] * np.maximum(i["x"] - p["t"], 0.0)

    physics = PhysicsModel(
        hinge,
        {"a": Uniform(-5.0, 5.0), "c": Uniform(0.0, 4.0), "t": Uniform(0.0, 30.0)},
        inputs=["x"],
        name="hinge",
    )
    x = np.linspace(0.0, 10.0, 25)
    rng = np.random.default_rng(SEED)
    y = hinge({"x": x}, {"a": 1.0, "c": 2.0, "t": 4.0}) + rng.normal(0.0, 0.1, x.size)
    return physics, CalibrationData({"x": x}, y, noise_sd=0.1)


def _quiet_calibrate(physics, data, **kwargs):
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        cal = calibrate(physics, data, chains=1, random_seed=SEED, warn=False, **kwargs)
    return cal, [w for w in seen if issubclass(w.category, UserWarning)]


def test_a_parameter_without_effect_at_the_centre_is_identified_at_the_mode():
    physics, data = _hinge()
    cal, seen = _quiet_calibrate(physics, data, draws=30, tune=30, slow_warning_s=None)
    centre, at_mode = cal.identifiability, cal.identifiability_at_mode
    assert not centre.identifiable
    assert {name for found in centre.non_identifiable_sets for name in found} == {"c", "t"}
    assert at_mode.identifiable and at_mode.weak_direction == {}
    assert abs(at_mode.point["t"] - 4.0) < 0.5  # the check ran at the fit, not the centre
    texts = [str(w.message) for w in seen if w.category is IdentifiabilityWarning]
    assert any("prior centre" in t for t in texts)
    assert not any("posterior mode" in t for t in texts)
    record = json.loads(cal.provenance()["presampling"])
    assert record["identifiability_at_mode"]["identifiable"] is True
    assert record["mode"]["t"] == pytest.approx(at_mode.point["t"])
    assert record["cost"] is None  # slow_warning_s=None


def test_a_structural_product_ridge_is_named_at_the_mode():
    x = np.linspace(0.5, 2.0, 12)
    physics = PhysicsModel(
        lambda i, p: p["a"] * p["b"] * i["x"],
        {"a": Uniform(0.1, 10.0), "b": Uniform(0.5, 20.0)},
        inputs=["x"],
        name="product",
    )
    rng = np.random.default_rng(SEED)
    data = CalibrationData({"x": x}, 3.0 * x + rng.normal(0.0, 0.05, x.size), noise_sd=0.05)
    cal, seen = _quiet_calibrate(physics, data, draws=20, tune=20, slow_warning_s=1e-3)
    report = cal.identifiability_at_mode
    assert report.rank == 1 and report.structural is True
    a, b = report.point["a"], report.point["b"]
    assert a * b == pytest.approx(3.0, rel=0.02)  # the mode lies on the ridge a·b = 3
    (direction,) = report.null_directions  # Δa/a = -Δb/b along the ridge
    assert direction["b"] / direction["a"] == pytest.approx(-b / a, rel=1e-3)
    (text,) = [
        str(w.message)
        for w in seen
        if w.category is IdentifiabilityWarning and "posterior mode" in str(w.message)
    ]
    assert "rank 1 of 2" in text and "entering only as a·b" in text and "structural" in text
    # a (deliberately tiny) time threshold: the slow-run warning names the ridge too
    (slow,) = [str(w.message) for w in seen if w.category is SlowSamplingWarning]
    assert "at the posterior mode a and b are confounded" in slow


@pytest.mark.slow  # 17 s idle, ~70-150 s loaded: the mode search and a <= 20 s probe
def test_dielectric_m0_is_identified_at_the_mode_and_its_cost_is_estimated():
    """The stand-in's trap parameters have no effect at the prior centre (rank 4 of 7) but
    are informed at the fit; the weak direction there is the Fowler–Nordheim B² ridge
    (Δln Φ_B : Δln m* ≈ 1 : -3); the pre-sampling probe's leapfrog steps per draw are
    within 2.5× of a short sampled run's."""
    from kohpymc.examples import dielectric as d
    from kohpymc.identifiability import model_taylor_check
    from kohpymc.model import compose_model
    from kohpymc.presampling import PreSampling
    from kohpymc.reparameterization import plan
    from kohpymc.sampling import _user_starts
    from kohpymc.value_space import value_space

    data, _ = d.split_calibration_validation(d.generate_data(seed=0))
    physics, form = d.physics_model(), d.formulations()["M0"]
    fit = d.least_squares_fit(data)
    built = compose_model(physics, data, form)
    plain = compose_model(physics, data, form, marginalize=False)
    assert model_taylor_check(plain).rank < 7
    space = value_space(built.model)
    reparam = plan(space, _user_starts(space, [fit]), seed=SEED)
    hook = PreSampling(plain, physics, data.inputs, label="M0", target_accept=0.9)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        settings = dict(draws=1000, tune=1000, chains=4, cores=2, seed=SEED, sampler="nutpie")
        hook(space, reparam, settings)
    report = hook.report
    assert report.identifiable and set(report.weak_direction) == {"phi_B", "m_eff"}
    log_ratio = (report.weak_direction["m_eff"] / report.point["m_eff"]) / (
        report.weak_direction["phi_B"] / report.point["phi_B"]
    )
    assert -3.5 < log_ratio < -2.5  # B ∝ √m*·Φ_B^1.5 fixed: Δln m* = -3 Δln Φ_B
    assert any("practically non-identifiable" in str(w.message) for w in seen)
    # the probe's count against a sampled run's (it was 20-300 when this plan needed 59-69
    # steps per draw; the plans since need ~7-10, and the range was no longer the claim)
    assert hook.cost.steps_from == "probe"
    from kohpymc.sampling import sample_posterior

    idata, _ = sample_posterior(
        built.model, draws=300, tune=300, chains=1, cores=1, random_seed=SEED,
        starts=[fit], space=space, target_accept=0.9,
    )  # fmt: skip
    sampled = float(idata.sample_stats["n_steps"].mean())
    assert sampled / 2.5 < hook.cost.steps_per_draw < 2.5 * sampled, (sampled, hook.cost)


def test_probe_counts_more_steps_on_a_correlated_gaussian():
    """nutpie adapts a diagonal mass matrix: a correlation of 0.999 (sd ratio of the
    principal axes √(1999/1) ≈ 45) leaves trajectories many times longer than on an
    isotropic Gaussian."""
    rho = 0.999
    precision = np.linalg.inv(np.array([[1.0, rho], [rho, 1.0]]))

    def correlated(z):
        return -0.5 * z @ precision @ z, -precision @ z

    def isotropic(z):
        return -0.5 * z @ z, -z

    easy_warm_up, easy, _ = probe_steps(isotropic, 2, iterations=100, seed=SEED)
    hard_warm_up, hard, done = probe_steps(correlated, 2, iterations=100, seed=SEED)
    assert done == 100
    assert easy <= 8 and easy_warm_up <= 16
    assert hard >= 5 * easy and hard_warm_up >= 5 * easy_warm_up


def test_probe_stops_at_its_time_budget():
    def slow(z):
        time.sleep(0.01)
        return -0.5 * z @ z, -z

    begin = time.perf_counter()
    warm_up, after, done = probe_steps(slow, 2, iterations=1000, seconds=0.5, seed=SEED)
    assert time.perf_counter() - begin < 3.0
    assert 0 < done < 1000 and warm_up >= 1 and not after > 3 * warm_up


def test_rates_split_the_warm_up_from_the_draws():
    from kohpymc.presampling import _rates

    # 10 warm-up iterations of 7 then 3 evaluations (5 each), then 2 draws of 4
    per = [7] * 5 + [3] * 5 + [4, 4]
    marks = list(np.cumsum(per))
    assert _rates(marks, marks[-1], 10) == (5.0, 4.0, 10)
    assert _rates(marks[:10], marks[9], 10) == (5.0, 3.0, 10)  # cut short: second half
    early = _rates(marks[:3], marks[2], 10)  # too few for a later rate
    assert early[0] == 7.0 and np.isnan(early[1]) and early[2] == 3
    none = _rates([], 12, 10)  # no iteration finished: a lower bound
    assert none[0] == 12.0 and np.isnan(none[1]) and none[2] == 0


def test_reasons_name_a_noisy_gradient_and_suggest_smc():
    from kohpymc.presampling import CostEstimate

    noisy = (
        "the gradient of the log density disagrees with finite differences of it "
        "(relative error 0.3 ...): ... or use sampler='smc'"
    )
    plan = Reparameterization(
        "affine", np.zeros(1), np.eye(1), Coordinates.identity(1), "", warnings=(noisy,)
    )
    cheap = CostEstimate(1e-5, 4.0, "probe", 8000, 900.0, threshold_s=600.0)
    reasons = slow_reasons(cheap, plan, None)
    assert reasons == [noisy]  # cheap evaluations and short trajectories: not the cause


def test_cost_estimate_warns_and_matches_the_measured_time():
    """5 ms of sleep per physics call (value and Jacobian: ~10 ms per evaluation): the
    estimate is within a factor 3 of the sampling time measured on the same run."""

    def value(i, p):
        time.sleep(0.005)
        return p["a"] * np.exp(-p["b"] * i["x"])

    def jacobian(i, p):
        time.sleep(0.005)
        e = np.exp(-p["b"] * i["x"])
        return np.column_stack([e, -p["a"] * i["x"] * e])

    physics = PhysicsModel(
        value,
        {"a": Uniform(0.0, 5.0), "b": Uniform(0.0, 3.0)},
        inputs=["x"],
        jacobian=jacobian,
        name="slow decay",
    )
    x = np.linspace(0.5, 2.0, 12)
    rng = np.random.default_rng(SEED)
    data = CalibrationData(
        {"x": x}, 2.0 * np.exp(-x) + rng.normal(0.0, 0.05, x.size), noise_sd=0.05
    )
    cal, seen = _quiet_calibrate(physics, data, draws=40, tune=40, slow_warning_s=1.0)
    (text,) = [str(w.message) for w in seen if w.category is SlowSamplingWarning]
    assert "kohpymc.Emulator" in text and "ms per log-density+gradient evaluation" in text
    cost = json.loads(cal.idata.attrs["presampling"])["cost"]
    assert cost["exceeds"] and cost["steps_from"] == "probe"
    assert 0.005 < cost["seconds_per_evaluation"] < 0.05
    measured = json.loads(cal.idata.attrs["sampling"])["timings_s"]["sampling"]
    assert measured / 3 < cost["estimated_seconds"] < 3 * measured, (cost, measured)


def test_a_failing_check_or_probe_is_noted_not_raised(monkeypatch):
    """The checks before sampling never stop a calibration: what failed is in the notes."""
    import kohpymc.presampling as presampling

    def broken(*args, **kwargs):
        raise RuntimeError("probe exploded\nsecond line")

    monkeypatch.setattr(presampling, "estimate_cost", broken)
    monkeypatch.setattr(presampling, "check_at_point", broken)
    physics, data = _hinge()
    cal, _ = _quiet_calibrate(physics, data, draws=10, tune=10, slow_warning_s=1.0)
    notes = json.loads(cal.idata.attrs["presampling"])["notes"]
    assert notes == [
        "identifiability at the mode skipped: RuntimeError: probe exploded",
        "sampling-time estimate skipped: RuntimeError: probe exploded",
    ]
    assert cal.identifiability_at_mode is None and cal.posterior["t"].size == 10
