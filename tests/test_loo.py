"""Exact Gaussian leave-one-out densities, checked against brute-force conditioning."""

from __future__ import annotations

import arviz as az
import numpy as np
import pymc as pm
import pytensor
import pytest
from pymc.model.transform.conditioning import remove_value_transforms
from scipy import stats

from kohpymc.examples import beam
from kohpymc.loo import gaussian_loo_log_density, loo_log_likelihood
from kohpymc.model import build_model, compose_model


def _brute_force_loo(y, mu, cov):
    """Condition on the other n-1 rows by a dense solve, one row at a time."""
    n = y.size
    out = np.empty(n)
    for i in range(n):
        rest = np.delete(np.arange(n), i)
        k_ir = cov[i, rest]
        w = np.linalg.solve(cov[np.ix_(rest, rest)], k_ir)
        mean = mu[i] + w @ (y[rest] - mu[rest])
        var = cov[i, i] - k_ir @ w
        out[i] = stats.norm.logpdf(y[i], mean, np.sqrt(var))
    return out


def test_matches_brute_force_conditioning_for_a_batch_of_covariances():
    rng = np.random.default_rng(5)
    n = 12
    x = np.sort(rng.uniform(0, 10, n))
    y = rng.normal(size=n)
    mus, covs = [], []
    for ls, amp in [(0.5, 1.0), (3.0, 2.0), (20.0, 0.3)]:
        k = amp**2 * np.exp(-0.5 * (x[:, None] - x[None, :]) ** 2 / ls**2)
        covs.append(k + 0.1 * np.eye(n))
        mus.append(rng.normal(size=n))
    got = gaussian_loo_log_density(y, np.array(mus), np.array(covs))
    assert got.shape == (3, n)
    for b in range(3):
        np.testing.assert_allclose(got[b], _brute_force_loo(y, mus[b], covs[b]), rtol=1e-9)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="shapes"):
        gaussian_loo_log_density(np.zeros(3), np.zeros(3), np.eye(2))


def test_gp_calibration_stores_loo_conditionals(beam_calibrations, beam_physics, beam_data):
    idata = beam_calibrations("M4").idata
    ll = idata.log_likelihood["y"]
    assert ll.dims == ("chain", "draw", "obs")
    assert idata.log_likelihood.attrs["pointwise"] == "loo_conditional"
    np.testing.assert_allclose(ll["x"].values, beam_data.inputs["x"])
    # the extracted mean and covariance reproduce PyMC's own joint log-likelihood
    model = build_model(beam_physics, beam_data, beam.formulations()["M4"])
    small = idata.posterior.isel(draw=slice(0, 5))
    joint = pm_joint_loglik(model, small)
    umodel = remove_value_transforms(model)
    rv = umodel["y"]
    mu, cov = umodel.replace_rvs_by_values(list(rv.owner.inputs[-2:]))
    names = [v.name for v in umodel.value_vars]
    fn = pytensor.function(umodel.value_vars, [mu, cov], on_unused_input="ignore")
    y = beam_data.y
    for c in range(small.sizes["chain"]):
        for d in range(small.sizes["draw"]):
            point = [small[k].values[c, d] for k in names]
            m, k = fn(*point)
            m = np.broadcast_to(m, y.shape)
            ref = stats.multivariate_normal.logpdf(y, m, k)
            assert joint[c, d] == pytest.approx(ref, rel=1e-9)
            np.testing.assert_allclose(
                ll.values[c, d], _brute_force_loo(y, m, k), rtol=1e-8, atol=1e-10
            )
    # PSIS-LOO now sees n observations
    loo = az.loo(idata, pointwise=True)
    assert loo.n_data_points == beam_data.n
    assert float(np.max(loo.pareto_k)) < 0.7


def pm_joint_loglik(model, posterior):
    ds = pm.compute_log_likelihood(
        az.InferenceData(posterior=posterior),
        model=model,
        extend_inferencedata=False,
        progressbar=False,
    )
    return ds["y"].values


def test_refuses_non_gaussian_observed(beam_physics, beam_data, beam_calibrations):
    from kohpymc.discrepancy import IIDGaussian

    built = compose_model(beam_physics, beam_data, IIDGaussian(), marginalize=False)
    with pytest.raises(ValueError, match="M2: exact leave-one-out needs the likelihood's covar"):
        loo_log_likelihood(beam_calibrations("M2").posterior, built)


def test_batched_log_likelihood_equals_pymcs_loop_over_draws():
    """kohpymc.loo.compute_log_likelihood (all draws in one numpy call) against PyMC's
    per-draw compiled function: a positive and a vector parameter, named dims, a
    three-term mean; values to 1e-12, same dims and coords."""
    import xarray as xr

    from kohpymc.loo import _batched_log_likelihood, compute_log_likelihood

    x = np.linspace(0.0, 1.0, 6)
    with pm.Model(coords={"obs": np.arange(6)}) as model:
        a = pm.Normal("a", 0.0, 1.0, shape=2)
        s = pm.HalfNormal("s", 1.0)
        pm.Normal("y", a[0] + a[1] * x + 0.1 * s, s, observed=np.sin(3 * x), dims="obs")
    rng = np.random.default_rng(11)
    post = xr.Dataset(
        {
            "a": (("chain", "draw", "a_dim_0"), rng.normal(size=(2, 30, 2))),
            "s": (("chain", "draw"), rng.uniform(0.2, 2.0, size=(2, 30))),
        },
        coords={"chain": [0, 1], "draw": np.arange(30)},
    )
    idata = az.InferenceData(posterior=post)
    assert _batched_log_likelihood(post, model) is not None
    got = compute_log_likelihood(idata, model)
    want = pm.compute_log_likelihood(
        idata, model=model, extend_inferencedata=False, progressbar=False
    )
    assert got["y"].dims == want["y"].dims == ("chain", "draw", "obs")
    np.testing.assert_allclose(got["y"].values, want["y"].values, rtol=1e-12)
