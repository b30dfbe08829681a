import itertools

import arviz as az
import numpy as np
import pytest

from kohpymc.combination import combine_posteriors, reliability_weights

SEED = 23


def _idata(mean, seed, n=400):
    rng = np.random.default_rng(seed)
    return az.from_dict(
        posterior={"E": rng.normal(mean, 1.0, size=(2, n)), f"only_{seed}": np.zeros((2, n))},
        predictions={"y_model": rng.normal(mean, 0.1, size=(2, n, 3))},
        dims={"y_model": ["pred"]},
    )


def test_weights_properties():
    mu = {"M0": 0.5, "M1": 0.66, "M2": 0.55, "M3": 0.36}
    w = reliability_weights(mu)
    assert sum(w.values()) == pytest.approx(1.0) and min(w.values()) >= 0
    for perm in itertools.permutations(mu):
        assert reliability_weights({k: mu[k] for k in perm}) == pytest.approx(w)
    assert reliability_weights({"a": 0.4, "b": 0.4}) == {"a": 0.5, "b": 0.5}
    with pytest.raises(ValueError, match="all mu_r are zero"):
        reliability_weights({"a": 0.0})
    with pytest.raises(ValueError, match="non-negative"):
        reliability_weights({"a": -0.1, "b": 1.0})


def test_mixture_draw_counts_origin_and_moments():
    results = {"A": _idata(0.0, 1), "B": _idata(10.0, 2), "C": _idata(20.0, 3)}
    preds = dict(results)
    weights = {"A": 0.2, "B": 0.5, "C": 0.3}
    mix = combine_posteriors(results, weights, predictions=preds, draws=800, random_seed=SEED)
    post = mix.posterior
    assert post.sizes["draw"] == 800 and post.sizes["chain"] == 1
    assert list(post.data_vars) == ["E"]  # only the shared variable
    origin = post["formulation"].values
    counts = {k: int((origin == k).sum()) for k in weights}
    assert counts == {"A": 160, "B": 400, "C": 240}
    # mixture mean = Σ w_i mean_i (sd of the estimate ~ 0.04)
    assert float(post["E"].mean()) == pytest.approx(0.5 * 10 + 0.3 * 20, abs=0.2)
    # predictions follow the same draws
    np.testing.assert_array_equal(mix.predictions["formulation"].values, origin)
    by_origin = mix.predictions["y_model"].values[0].mean(axis=1)
    assert np.all(np.abs(by_origin[origin == "C"] - 20) < 1)


def test_identical_models_equal_weights_reproduce_the_posterior():
    a = _idata(3.0, 7)
    mix = combine_posteriors({"A": a, "B": a}, {"A": 1, "B": 1}, random_seed=SEED)
    values = np.sort(mix.posterior["E"].values.ravel())
    assert np.all(np.isin(values, a.posterior["E"].values))
    assert values.size == 800


def test_bad_weights():
    with pytest.raises(KeyError, match="without results"):
        combine_posteriors({"A": _idata(0, 1)}, {"A": 1.0, "Z": 1.0})
    with pytest.raises(ValueError, match="positive weight"):
        combine_posteriors({"A": _idata(0, 1)}, {"A": 0.0})
