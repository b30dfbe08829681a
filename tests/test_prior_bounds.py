"""A posterior against a bound of its prior: found at the mode and in the draws, and said."""

import json
import warnings

import numpy as np
import pytest

from kohpymc import CalibrationData, PhysicsModel, Uniform, calibrate
from kohpymc.prior_bounds import PriorBoundWarning, against_bounds

SEED = 15


def _line(truth):
    """y = a·x with a ~ Uniform(0.5, 1.5), data generated at ``a = truth``."""
    physics = PhysicsModel(
        lambda i, p: p["a"] * i["x"], {"a": Uniform(0.5, 1.5)}, inputs=["x"], name="line"
    )
    x = np.linspace(1.0, 3.0, 20)
    rng = np.random.default_rng(SEED)
    return physics, CalibrationData(
        {"x": x}, truth * x + rng.normal(0.0, 0.1, x.size), noise_sd=0.1
    )


def _calibrate(truth):
    physics, data = _line(truth)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        cal = calibrate(physics, data, draws=200, tune=200, chains=1, random_seed=SEED)
    texts = [str(w.message) for w in seen if w.category is PriorBoundWarning]
    return cal, texts


def test_truth_outside_the_box_is_said_before_and_after_sampling():
    cal, texts = _calibrate(2.0)
    assert len(texts) == 2
    assert all(
        t.startswith("a: the posterior lies against its upper prior bound 1.5") for t in texts
    )
    assert "at the posterior mode" in texts[0] and "in the posterior draws" in texts[1]
    before = json.loads(cal.idata.attrs["presampling"])["prior_bounds"]
    after = json.loads(cal.idata.attrs["sampling"])["prior_bounds"]
    assert [(h["parameter"], h["side"], h["evidence"]) for h in before] == [("a", "upper", "mode")]
    assert [(h["parameter"], h["side"], h["evidence"]) for h in after] == [("a", "upper", "draws")]
    assert 1.49 < before[0]["value"] < 1.5 and after[0]["measure"] > 0.5


def test_truth_inside_the_box_is_not_said():
    cal, texts = _calibrate(1.0)
    assert texts == []
    assert json.loads(cal.idata.attrs["presampling"])["prior_bounds"] == []
    assert json.loads(cal.idata.attrs["sampling"])["prior_bounds"] == []


@pytest.mark.parametrize(
    ("mode", "sd", "expected"),
    [
        (0.04, 0.03, ["lower"]),
        (0.05, 0.03, []),
        (0.5, 0.2, []),
        (0.975, 0.02, ["upper"]),
        (0.96, 0.02, []),
        (0.9, 0.02, []),
    ],
)
def test_mode_criterion_counts_laplace_sds(mode, sd, expected):
    hits = against_bounds(
        ["a"], np.array([0.0]), np.array([1.0]), mode=np.array([mode]), sd=np.array([sd])
    )
    assert [h.side for h in hits] == expected


def test_draw_criterion_counts_the_share_at_the_bound():
    rng = np.random.default_rng(SEED)
    flat = rng.uniform(0.0, 1.0, size=(4000, 1))
    piled = 1.0 - rng.exponential(0.002, size=(4000, 1))
    assert (
        against_bounds(["a"], np.array([0.0]), np.array([1.0]), draws=flat, evidence="draws") == []
    )
    hits = against_bounds(["a"], np.array([0.0]), np.array([1.0]), draws=piled, evidence="draws")
    assert [(h.side, h.bound) for h in hits] == [("upper", 1.0)] and hits[0].measure > 0.9


def test_a_posterior_as_wide_as_the_box_is_not_against_either_bound():
    """The beam's M3 in CI: E's mode 174 in [50, 300] with a Laplace sd of ~90 was reported
    against both bounds; ±2 sds do not fit in the box, so it is the prior's spread."""
    hits = against_bounds(
        ["E"], np.array([50.0]), np.array([300.0]), mode=np.array([174.0]), sd=np.array([90.0])
    )
    assert hits == []


def test_draws_clear_of_a_bound_on_their_own_scale_are_not_against_it():
    """tau ~ 8e-4 under LogUniform(1e-6, 1): every draw lies within 1 % of the prior width
    of the lower bound, but the bound is far below the posterior on its own scale."""
    rng = np.random.default_rng(SEED)
    tau = np.exp(rng.normal(np.log(8e-4), 0.1, size=(4000, 1)))
    hits = against_bounds(["tau"], np.array([1e-6]), np.array([1.0]), draws=tau, evidence="draws")
    assert hits == []
    piled = 1e-6 + rng.exponential(1e-5, size=(4000, 1))  # the same box, truncated at 1e-6
    hits = against_bounds(["tau"], np.array([1e-6]), np.array([1.0]), draws=piled, evidence="draws")
    assert [h.side for h in hits] == ["lower"]


def test_a_posterior_over_decades_under_a_wide_log_box_is_judged_on_the_log_scale():
    """τ spread over 1e-5..1e-2 under LogUniform(1e-6, 1): every draw is within 1 % of the
    box's width of 1e-6 and its 1st percentile 0.1 % of its range from it, so it was
    reported against the bound; on its own (log) scale it stays a decade clear.  A
    posterior piled against 1e-6 is still found."""
    rng = np.random.default_rng(SEED)
    lower, upper = np.array([1e-6]), np.array([1.0])
    spread = np.exp(rng.uniform(np.log(1e-5), np.log(1e-2), 4000))[:, None]
    assert against_bounds(["tau"], lower, upper, draws=spread, evidence="draws") == []
    piled = 1e-6 * np.exp(np.abs(rng.normal(0.0, 0.3, 4000)))[:, None]
    hits = against_bounds(["tau"], lower, upper, draws=piled, evidence="draws")
    assert [(h.parameter, h.side, h.bound) for h in hits] == [("tau", "lower", 1e-6)]


def test_draws_over_the_whole_box_are_not_against_either_bound():
    """A replicate of an unseen creep study's simulation check: data of pure noise leave
    A ~ LogUniform(1e-2, 1e8) at its prior (quantiles 0.04 ... 4.7e7, median 370).  84 % of
    the draws lie within 1 % of the box's width (1e6) of 0.01 and both tails reach a
    bound, so it was reported against the lower one; it is the prior's spread.  A
    posterior cut off by one bound only is still found."""
    rng = np.random.default_rng(SEED)
    lower, upper = np.array([1e-2]), np.array([1e8])
    prior = np.exp(rng.uniform(np.log(1e-2), np.log(1e8), 4000))[:, None]
    assert against_bounds(["A"], lower, upper, draws=prior, evidence="draws") == []
    lower_half = np.exp(rng.uniform(np.log(1e-2), np.log(1e3), 4000))[:, None]
    hits = against_bounds(["A"], lower, upper, draws=lower_half, evidence="draws")
    assert [(h.side, h.bound) for h in hits] == [("lower", 1e-2)]


def test_a_mode_decades_above_a_wide_log_box_bound_is_judged_on_the_log_scale():
    """Arrhenius prefactor A ~ LogUniform(1e-9, 1e-3), mode 5.8e-5 with a linearised Laplace
    sd of 1.1e-4 (an unseen viscosity study): 0.5 sd from 1e-9 in A's units, so it was
    reported against the bound, but 5.8 sds (ln(5.8e-5 / 1e-9) / (1.1e-4 / 5.8e-5)) clear
    of it on the log scale.  Modes near either bound of the same box are still found, with
    the measure the linear one agrees with there (ln(x/a) ≈ (x − a)/a)."""
    lower, upper = np.array([1e-9]), np.array([1e-3])
    far = against_bounds(["A"], lower, upper, mode=np.array([5.8e-5]), sd=np.array([1.1e-4]))
    assert far == []
    low = against_bounds(["A"], lower, upper, mode=np.array([1.01e-9]), sd=np.array([1e-11]))
    assert [h.side for h in low] == ["lower"] and low[0].measure == pytest.approx(1.0, rel=0.01)
    high = against_bounds(["A"], lower, upper, mode=np.array([0.99e-3]), sd=np.array([1e-5]))
    assert [h.side for h in high] == ["upper"] and high[0].measure == pytest.approx(1.0, rel=0.02)
