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


def test_replicates_define_the_measurement_distribution():
    ym = _draws(np.full((1, 5, 4), 1.0))
    val = CalibrationData({"x": [0.0, 0.0, 1.0, 1.0]}, [0.8, 1.2, 3.0, 3.4], replicates="inputs")
    res = reliability(ym, val, tolerance=0.5)
    from scipy.stats import norm

    sd0 = np.std([0.8, 1.2], ddof=1)
    expected0 = norm.cdf((1.5 - 1.0) / sd0) - norm.cdf((0.5 - 1.0) / sd0)
    assert res.pointwise.values[0] == pytest.approx(expected0)
    assert res.pointwise.values[2] < 1e-6


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
