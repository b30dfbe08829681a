"""Batched posterior predictive draws against their moments computed from the draws."""

import arviz as az
import numpy as np
import pymc as pm
import xarray as xr

from kohpymc.predictive import _batched, sample_predictions

X = np.array([0.0, 1.0, 2.0])


def _posterior(seed: int = 0, chains: int = 2, draws: int = 3000) -> az.InferenceData:
    rng = np.random.default_rng(seed)
    shape = (chains, draws)
    post = xr.Dataset(
        {
            "a": (("chain", "draw"), rng.normal(1.0, 0.2, shape)),
            "b": (("chain", "draw"), rng.normal(-0.5, 0.1, shape)),
            "s": (("chain", "draw"), rng.uniform(0.5, 1.5, shape)),
        }
    )
    return az.InferenceData(posterior=post)


def _model(non_centred: bool = False) -> pm.Model:
    """``y_pred = a + b x + δ + ε``, δ ~ N(0, s) (a sized draw whose mean is constant)."""
    with pm.Model(coords={"pred": np.arange(X.size)}) as model:
        a = pm.Normal("a")
        b = pm.Normal("b")
        s = pm.HalfNormal("s")
        y_model = pm.Deterministic("y_model", a + b * X, dims="pred")
        if non_centred:  # a draw that depends on no posterior value
            delta = s * pm.Normal("delta_white", 0.0, 1.0, dims="pred")
        else:
            delta = pm.Normal("delta", 0.0, s, dims="pred")
        pm.Normal("y_pred", y_model + delta, 0.5, dims="pred")
    return model


def test_batched_draws_have_the_moments_of_the_posterior():
    idata = _posterior()
    pred = _batched(idata.posterior, _model(), ["y_model", "y_pred"], 1)
    assert pred is not None  # the batched path ran
    y = pred.predictions["y_pred"]
    assert y.dims == ("chain", "draw", "pred")
    post = idata.posterior
    line = (post["a"] + post["b"] * xr.DataArray(X, dims="pred")).values
    np.testing.assert_allclose(pred.predictions["y_model"].values, line)
    n = y.sizes["chain"] * y.sizes["draw"]
    expected_mean = line.mean(axis=(0, 1))
    expected_var = line.var(axis=(0, 1)) + float((post["s"] ** 2).mean()) + 0.25
    mean = y.mean(("chain", "draw")).values
    assert np.all(np.abs(mean - expected_mean) < 4 * np.sqrt(expected_var / n))
    var = y.var(("chain", "draw")).values
    assert np.all(np.abs(var / expected_var - 1) < 4 * np.sqrt(2 / n) * 1.5)


def test_batched_draws_repeat_with_the_seed_and_match_pymc_in_distribution():
    idata, model = _posterior(seed=1), _model()
    first = sample_predictions(idata, model, ["y_pred"], random_seed=7)
    again = sample_predictions(idata, model, ["y_pred"], random_seed=7)
    np.testing.assert_array_equal(first.predictions["y_pred"], again.predictions["y_pred"])
    with model:
        ref = pm.sample_posterior_predictive(
            idata, var_names=["y_pred"], predictions=True, random_seed=8, progressbar=False
        )
    a, b = first.predictions["y_pred"], ref.predictions["y_pred"]
    n = a.sizes["chain"] * a.sizes["draw"]
    se = np.sqrt((a.var(("chain", "draw")) + b.var(("chain", "draw"))) / n)
    assert np.all(np.abs(a.mean(("chain", "draw")) - b.mean(("chain", "draw"))) < 4 * se)


def test_a_draw_independent_of_the_posterior_is_left_to_pymc():
    idata, model = _posterior(seed=2, draws=200), _model(non_centred=True)
    assert _batched(idata.posterior, model, ["y_pred"], 3) is None
    pred = sample_predictions(idata, model, ["y_pred"], random_seed=3)
    with model:
        ref = pm.sample_posterior_predictive(
            idata, var_names=["y_pred"], predictions=True, random_seed=3, progressbar=False
        )
    np.testing.assert_array_equal(pred.predictions["y_pred"], ref.predictions["y_pred"])
