import warnings

import numpy as np
import pytest
import xarray as xr

from kohpymc import CalibrationData
from kohpymc.validation import reliability

SEED = 5


def _draws(values):
    values = np.asarray(values, dtype=float)
    return xr.DataArray(values, dims=("chain", "draw", "pred"))


def test_matches_brute_force_monte_carlo():
    """Two-layer brute force: sample y_D and y_m, count |y_D - y_m| < ε."""
    rng = np.random.default_rng(SEED)
    ym = rng.normal([1.0, 2.5, -0.5], [0.4, 0.8, 0.2], size=(2, 500, 3))
    val = CalibrationData({"x": [0.0, 1.0, 2.0]}, [1.2, 2.0, 0.3], noise_sd=0.3)
    res = reliability(_draws(ym), val, tolerance=0.75)
    n = 400
    yd = rng.normal(val.y, 0.3, size=(n, 2, 500, 3))  # a fresh y_D for every pair
    brute = (np.abs(yd - ym[None]) < 0.75).mean(axis=(0, 1, 2))
    # binomial error of 400 000 Bernoulli trials per point: < 0.001
    np.testing.assert_allclose(res.pointwise.values, brute, atol=4e-3)
    assert res.mu_r == pytest.approx(res.pointwise.values.mean())


def test_weights_and_errors():
    ym = _draws(np.zeros((1, 10, 2)))
    val = CalibrationData({"x": [0.0, 1.0]}, [0.0, 5.0], noise_sd=1.0)
    res = reliability(ym, val, tolerance=1.0, weights=[1.0, 0.0])
    assert res.mu_r == pytest.approx(0.6826894921, rel=1e-9)
    with pytest.raises(ValueError, match="tolerance"):
        reliability(ym, val, tolerance=0.0)
    with pytest.raises(ValueError, match="2 predicted points but 3"):
        reliability(ym, CalibrationData({"x": [0, 1, 2.0]}, [0, 0, 0.0], noise_sd=1), 1.0)
    with pytest.raises(ValueError, match="noise sd"):
        reliability(ym, CalibrationData({"x": [0, 1.0]}, [0, 0.0]), 1.0)


def test_mcse_matches_spread_over_repeated_posteriors():
    rng = np.random.default_rng(SEED)
    val = CalibrationData({"x": np.arange(5.0)}, np.zeros(5), noise_sd=0.5)
    results = [
        reliability(_draws(rng.normal(0.3, 0.6, size=(2, 200, 5))), val, 0.5) for _ in range(200)
    ]
    spread = np.std([r.mu_r for r in results])
    reported = np.mean([r.mcse for r in results])
    assert reported == pytest.approx(spread, rel=0.2)


def test_reliability_near_one_has_a_finite_mcse_and_no_warning():
    """Predictions ~6.5 noise sds inside the tolerance: r = 1 - 1e-11 with a tiny spread.

    ArviZ's variance of such values came out negative (a NaN MCSE and a numpy
    RuntimeWarning that reached the user).  The reference is the MCSE of the per-draw
    reliabilities' deviations computed in long double from the same draws.
    """
    rng = np.random.default_rng(SEED)
    val = CalibrationData({"x": np.arange(6.0)}, np.zeros(6), noise_sd=1e-4)
    ym = rng.normal(0.0, 1e-5, size=(2, 500, 6))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = reliability(_draws(ym), val, tolerance=6.5e-4)
    assert 1 - 1e-9 < res.mu_r < 1.0
    # independent draws: MCSE ≈ sd / sqrt(n), the sd from the exact erfc tails
    from scipy.special import erfc

    tails = 0.5 * (
        erfc((6.5e-4 - ym) / 1.4142135623730951e-4) + erfc((6.5e-4 + ym) / 1.4142135623730951e-4)
    )
    deviation = tails.mean(axis=2)  # 1 - r per draw
    assert res.mcse == pytest.approx(deviation.std() / np.sqrt(deviation.size), rel=0.2)
    constant = reliability(_draws(np.zeros((2, 10, 6))), val, tolerance=6.5e-4)
    assert constant.mcse == 0.0


def test_replicates_give_the_pooled_sd_of_eq28_not_each_groups_own():
    ym = _draws(np.full((1, 5, 4), 1.0))
    y = [0.8, 1.2, 3.0, 3.4]
    val = CalibrationData({"x": [0.0, 0.0, 1.0, 1.0]}, y, replicates="inputs")
    res = reliability(ym, val, tolerance=0.5)
    from scipy.stats import norm

    pooled = np.sqrt(((0.2**2 + 0.2**2) + (0.2**2 + 0.2**2)) / 2)  # Eq. 28 by hand
    assert val.noise_sd == pytest.approx(pooled)
    expected = norm.cdf((1.5 - 0.8) / pooled) - norm.cdf((0.5 - 0.8) / pooled)
    assert res.pointwise.values[0] == pytest.approx(expected)  # each row its own D
    assert res.pointwise.values[2] < 1e-6


def test_per_draw_sigma_matches_brute_force_monte_carlo():
    """σ varies over the draws: draw s of y_m is scored against y_D ~ N(D, σ_s²)."""
    rng = np.random.default_rng(SEED)
    ym = rng.normal([1.0, 2.5], [0.4, 0.3], size=(2, 400, 2))
    sigma = xr.DataArray(rng.uniform(0.1, 1.0, size=(2, 400)), dims=("chain", "draw"))
    val = CalibrationData({"x": [0.0, 1.0]}, [1.2, 2.0])
    res = reliability(_draws(ym), val, tolerance=0.5, noise_sd=sigma)
    n = 500
    yd = val.y + sigma.values[None, ..., None] * rng.normal(size=(n, 2, 400, 2))
    brute = (np.abs(yd - ym[None]) < 0.5).mean(axis=(0, 1, 2))
    np.testing.assert_allclose(res.pointwise.values, brute, atol=4e-3)
    with pytest.raises(ValueError, match="per-draw noise sd has"):
        reliability(_draws(ym), val, 0.5, noise_sd=sigma.isel(draw=slice(0, 10)))


def test_iid_discrepancy_scores_depend_only_on_the_sum_of_variances():
    """M2 with unknown noise: y_m = G + δ with δ ~ N(0, σ_δ²) fresh per draw and σ_obs per
    draw; any split of the same σ_obs² + σ_δ² gives the r(x) of the sum (closed form)."""
    from scipy.stats import norm

    rng = np.random.default_rng(SEED)
    g, d, eps, total = 1.0, 1.4, 0.5, 0.6
    for share in (0.2, 0.5, 0.9):
        s_obs, s_delta = total * np.sqrt(share), total * np.sqrt(1 - share)
        ym = g + s_delta * rng.normal(size=(4, 20_000, 1))
        sigma = xr.DataArray(np.full((4, 20_000), s_obs), dims=("chain", "draw"))
        val = CalibrationData({"x": [0.0]}, [d])
        res = reliability(_draws(ym), val, eps, noise_sd=sigma)
        exact = norm.cdf((g + eps - d) / total) - norm.cdf((g - eps - d) / total)
        assert res.mu_r == pytest.approx(exact, abs=3e-3)


def test_validation_noise_prefers_a_shared_sd_and_else_uses_the_draws():
    from kohpymc import IIDGaussian
    from kohpymc.validation import shared_validation_noise, validation_noise

    post = xr.Dataset({"sigma_obs": (("chain", "draw"), np.full((2, 5), 0.4))})
    unknown = CalibrationData({"x": [0.0, 1.0]}, [1.0, 2.0])
    known = CalibrationData({"x": [0.0, 1.0]}, [1.0, 2.0], noise_sd=0.2)
    replicated = CalibrationData({"x": [0.0, 0.0, 1.0, 1.0]}, [1, 1.2, 2, 2.4], replicates="inputs")
    assert validation_noise(known, unknown, post).source == "validation noise_sd"
    assert validation_noise(unknown, known, post).source == "calibration noise_sd"
    pooled = validation_noise(replicated, unknown, post)
    assert pooled.source == "pooled from the validation replicates (Eq. 28)"
    assert shared_validation_noise(unknown, unknown) is None
    drawn = validation_noise(unknown, unknown, post, IIDGaussian())
    assert drawn.per_draw and drawn.to_dict()["sd"] == pytest.approx(0.4)
    assert "sigma_obs² + delta_sd²" in drawn.note
    with pytest.raises(ValueError, match="no noise sd for the validation data"):
        validation_noise(unknown, unknown, xr.Dataset())


def test_beam_table1_conclusions(beam_calibrations, beam_physics, beam_data, beam_validation):
    """Paper Table 1 (calibrate at load 2.5, validate at 3.5, ε = 0.75 μm): the constant
    bias M1 predicts best and the x-only discrepancies M3/M4 worst.  Measured here:
    M0 0.25, M1 0.53, M2 0.50, M3 0.21, M4 0.23 (paper: 0.50, 0.66, 0.55, 0.36, 0.34)."""
    from kohpymc import combine_posteriors, predict, reliability_weights
    from kohpymc.examples import beam

    mu, preds = {}, {}
    for label in beam.formulations():
        preds[label] = predict(beam_calibrations(label), beam_validation, random_seed=SEED)
        res = reliability(preds[label], beam_validation, tolerance=0.75)
        assert res.mcse < 0.01
        mu[label] = res.mu_r
    assert max(mu, key=mu.get) == "M1"
    assert max(mu["M3"], mu["M4"]) < min(mu["M0"], mu["M1"], mu["M2"])
    weights = reliability_weights(mu)
    mix = combine_posteriors(
        {k: beam_calibrations(k).idata for k in mu}, weights, predictions=preds, random_seed=SEED
    )
    origin = mix.posterior["formulation"].values
    for label, w in weights.items():
        assert abs((origin == label).mean() - w) < 1e-3
    assert mix.predictions["y_model"].sizes["pred"] == beam_validation.n
