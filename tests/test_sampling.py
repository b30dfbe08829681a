"""The default sampler path on posteriors that are hard in natural units."""

import importlib.util
import json

import arviz as az
import numpy as np
import pytest

import kohpymc as kp
from kohpymc.examples import hard_posteriors
from kohpymc.sampling import choose_sampler

SEED = 20261123


@pytest.mark.parametrize(
    "name",
    # one hard case in the default suite; all three under `make test-slow`
    [
        pytest.param("arrhenius", marks=pytest.mark.slow),
        pytest.param("collinear", marks=pytest.mark.slow),
        "multiplicative",
    ],
)
def test_hard_posteriors_converge_at_default_settings(name):
    """Unknown noise, natural units, default settings: r̂ <= 1.01, bulk ESS >= 400 and no
    divergences for every parameter, and what the data inform covers the truth (4 sd)."""
    problem = hard_posteriors.all_problems(seed=3)[name]
    cal = kp.calibrate(problem.physics, problem.data, random_seed=SEED)
    summary = az.summary(cal.idata, var_names=[*problem.physics.parameters, "sigma_obs"])
    assert summary["r_hat"].max() <= 1.01, summary
    assert summary["ess_bulk"].min() >= 400, summary
    assert int(cal.idata.sample_stats.diverging.sum()) == 0
    assert cal.problems == []
    sampling = json.loads(cal.idata.attrs["sampling"])
    assert sampling["sampler"] == "nutpie"
    assert sampling["reparameterization"]["kind"] in ("affine", "log-affine")
    post = cal.idata.posterior
    if name == "multiplicative":
        informed = np.log(post["k"] * post["c"])
        truth = np.log(problem.truth["k"] * problem.truth["c"])
        assert abs(float(informed.mean()) - truth) < 4 * float(informed.std())
    else:
        for param, value in problem.truth.items():
            assert abs(float(post[param].mean()) - value) < 4 * float(post[param].std()), param


def test_sampler_choice_and_its_reason(monkeypatch):
    assert choose_sampler(None) == ("nutpie", "")
    assert choose_sampler("pymc") == ("pymc", "")
    with pytest.raises(ValueError, match="sampler must be one of"):
        choose_sampler("metropolis")
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda n, *a: None if n == "nutpie" else real(n, *a)
    )
    assert choose_sampler("nutpie") == ("pymc", "nutpie is not installed (pip install nutpie)")


def test_pymc_sampler_starts_at_the_mode_and_says_so():
    problem = hard_posteriors.linear(seed=1)
    cal = kp.calibrate(
        problem.physics, problem.data, sampler="pymc", draws=300, tune=300, chains=2,
        random_seed=SEED,
    )  # fmt: skip
    sampling = json.loads(cal.idata.attrs["sampling"])
    assert sampling["sampler"] == "pymc"
    assert cal.idata.attrs["sampler"] == "pymc"
    assert abs(float(cal.posterior["a"].mean()) - 2.5) < 4 * float(cal.posterior["a"].std())


def _two_load_beam():
    from kohpymc.examples import beam

    known = beam.generate_data((2.5, 3.0), seed=2026)
    data = kp.CalibrationData(
        {k: np.asarray(v) for k, v in known.inputs.items()}, known.y, output_name="u"
    )
    return beam.physics_model(), data


@pytest.mark.parametrize(
    "formulation, pair",
    [
        pytest.param(kp.IIDGaussian(), ("sigma_obs", "delta_sd"), marks=pytest.mark.slow),
        (kp.InputDependentGaussian(mean=["x", "P"]), ("sigma_obs", "delta_logvar")),
    ],
    ids=["M2", "M3"],
)
def test_noise_and_its_partner_get_variance_share_coordinates(formulation, pair):
    """With the noise sd unknown, σ_obs and the discrepancy's variance share one flat entry of
    value space each, found by name; the plan samples them as total sd and log ratio."""
    from kohpymc.model import compose_model
    from kohpymc.reparameterization import plan
    from kohpymc.sampling import variance_shares
    from kohpymc.value_space import value_space

    physics, data = _two_load_beam()
    space = value_space(compose_model(physics, data, formulation).model)
    shares = variance_shares(space, [("sigma_obs", *formulation.noise_partner())])
    assert shares is not None and shares.names == (pair,)
    ((i, j, scale),) = shares.pairs
    assert space.names[i] == "sigma_obs_log__"
    assert space.names[j].startswith(pair[1])  # the sd's log, or the first coefficient
    assert scale == (1.0 if pair[1] == "delta_sd" else 2.0)
    reparam = plan(space, seed=SEED, shares=shares)
    assert reparam.kind.startswith("variance-share"), reparam.reason
    assert "sigma_obs and " + pair[1] in reparam.reason


@pytest.mark.slow
@pytest.mark.parametrize("label", ["M0", "M1", "M2", "M3", "M4"])
def test_two_load_beam_with_unknown_noise_has_no_divergences(label):
    """Issue 15's acceptance: the two-load beam study written as a new user would (no noise
    sd, default formulations over x and P, default settings, the study's per-label seeds)."""
    from kohpymc.discrepancy.defaults import default_formulations
    from kohpymc.validation import derived_seed

    physics, data = _two_load_beam()
    formulation = default_formulations(physics.inputs)[label]
    cal = kp.calibrate(
        physics, data, formulation, random_seed=derived_seed(2026, label, 0), warn=False
    )
    assert int(cal.idata.sample_stats["diverging"].sum()) == 0, cal.problems
    assert float(az.rhat(cal.idata).to_array().max()) <= 1.01, cal.problems


def test_a_compiled_space_is_reused_with_new_shared_data():
    """sample_posterior(space=...) samples the posterior of the data now in the model's
    shared variables, without compiling: conjugate normal mean, exact posterior."""
    import pymc as pm

    from kohpymc.sampling import sample_posterior
    from kohpymc.value_space import value_space

    with pm.Model() as model:
        y = pm.Data("y_data", np.zeros(5))
        mu = pm.Normal("mu", 0.0, 10.0)
        pm.Normal("y", mu, 1.0, observed=y)
    space = value_space(model)
    new = np.array([2.0, 3.0, 4.0, 2.5, 3.5])
    pm.set_data({"y_data": new}, model=model)
    idata, report = sample_posterior(
        model, space=space, draws=400, tune=300, chains=2, random_seed=SEED
    )
    exact_mean, exact_sd = new.sum() / (5 + 1e-2), 1 / np.sqrt(5 + 1e-2)
    post = idata.posterior["mu"]
    assert abs(float(post.mean()) - exact_mean) < 0.25 * exact_sd  # ~5 Monte-Carlo SEs
    assert abs(float(post.std()) / exact_sd - 1) < 0.15
    assert report.timings["compile"] < 0.01
    with pm.Model() as other:
        pm.Normal("mu", 0.0, 1.0)
    with pytest.raises(ValueError, match="value_space"):
        sample_posterior(other, space=space)


def _oral_dose(inputs, params):
    """0/0 where ka = ke: at PyMC's initial point when both have the same prior."""
    ka, ke, t = np.float64(params["ka"]), np.float64(params["ke"]), inputs["t"]
    with np.errstate(all="ignore"):
        return ka / (ka - ke) * (np.exp(-ke * t) - np.exp(-ka * t))


def test_a_removable_singularity_at_the_initial_point_does_not_stop_compilation():
    """The NUMBA/C probe at PyMC's initial point (ka = ke) moves next to it instead of raising."""
    from kohpymc.model import compose_model
    from kohpymc.sampling import SamplingReport, _compiled_space

    prior = kp.LogUniform(0.01, 10)
    physics = kp.PhysicsModel(_oral_dose, {"ka": prior, "ke": prior}, inputs=["t"])
    t = np.linspace(0.25, 24, 12)
    y = _oral_dose({"t": t}, {"ka": 1.0, "ke": 0.1})
    built = compose_model(physics, kp.CalibrationData({"t": t}, y, noise_sd=0.01))
    report = SamplingReport(sampler="nutpie", requested="nutpie")
    space = _compiled_space(built.model, None, report)  # raised PhysicsModelError before
    assert report.compile_mode == "NUMBA"
    assert not np.isfinite(space.logp_dlogp_or_nan(space.initial)[0])
    moved = space.initial + 1e-3 * np.array([0.5, -1.0])
    assert np.isfinite(space.logp_dlogp(moved)[0])


def test_smc_statistics_of_chains_with_different_numbers_of_stages_are_padded(tmp_path):
    """PyMC's layout when SMC chains take 3 and 4 stages: a (1, 2) object array of lists.

    Seen with 4000 particles on a bimodal posterior ("setting an array element with a
    sequence" after sampling, every result lost).  Now (chain, stage) floats, NaN-padded,
    that NetCDF stores.
    """
    import xarray as xr

    from kohpymc.sampling import _smc_stats_per_stage

    stages = [[0.0, 0.2, 1.0], [0.0, 0.1, 0.5, 1.0]]
    cells = np.empty((1, 2), dtype=object)
    cells[0, 0], cells[0, 1] = stages
    stats = xr.Dataset({"beta": (("chain", "draw"), cells)})
    posterior = xr.Dataset({"a": (("chain", "draw"), np.zeros((2, 5)))})
    idata = _smc_stats_per_stage(az.InferenceData(posterior=posterior, sample_stats=stats))
    beta = idata.sample_stats["beta"]
    assert beta.dims == ("chain", "stage") and beta.dtype == float
    np.testing.assert_array_equal(beta.values[0], [0.0, 0.2, 1.0, np.nan])
    np.testing.assert_array_equal(beta.values[1], stages[1])
    idata.to_netcdf(str(tmp_path / "smc.nc"))


def test_default_cores_are_the_usable_cpus_or_a_dask_workers_threads():
    """One core per chain up to the CPUs this process may use; in a Dask worker up to its
    threads (a real LocalCluster), so single-threaded workers do not compete for cores."""
    import os

    from distributed import Client, LocalCluster

    from kohpymc.sampling import default_cores

    usable = len(os.sched_getaffinity(0))
    assert default_cores(4) == min(4, usable)
    assert default_cores(1) == 1
    for threads in (1, 3):
        with (
            LocalCluster(n_workers=1, threads_per_worker=threads, processes=False) as cluster,
            Client(cluster) as client,
        ):
            assert client.submit(default_cores, 4).result() == min(4, threads)
            assert client.submit(default_cores, 2).result() == min(2, threads)


def test_divergent_chains_are_sampled_again_at_a_higher_target_accept():
    """Neal's funnel, sampled without reparameterisation, diverges at 0.9: the chains run
    again at RETRY_TARGET_ACCEPT, whose draws are the result, and both counts are in the
    report.  A target the caller set is never overridden."""
    import pymc as pm

    from kohpymc.diagnostics import n_divergences
    from kohpymc.sampling import sample_posterior
    from kohpymc.second_run import RETRY_TARGET_ACCEPT

    with pm.Model() as funnel:
        v = pm.Normal("v", 0.0, 3.0)
        pm.Normal("x", 0.0, pm.math.exp(v / 2), shape=2)
    settings = dict(draws=300, tune=300, chains=2, cores=1, random_seed=5, reparameterize=False)
    idata, report = sample_posterior(funnel, **settings)
    second_run = report.second_run
    first, second = second_run["divergences"]
    assert first > 0 and "divergent" in second_run["reasons"][0]
    assert second_run["target_accept"] == [0.9, RETRY_TARGET_ACCEPT]
    assert n_divergences(idata) == second
    assert idata.posterior.sizes["draw"] == second_run["draws"][1]
    assert report.target_accept == RETRY_TARGET_ACCEPT
    assert json.loads(json.dumps(report.to_dict()))["second_run"] == second_run

    _, told = sample_posterior(funnel, target_accept=0.9, **settings)
    assert told.target_accept == 0.9
    assert told.second_run == {} or told.second_run["target_accept"] == [0.9, 0.9]


def test_slowly_mixing_chains_get_more_draws():
    """A Gaussian with correlation 0.999 sampled in PyMC's coordinates with trees cut at
    depth 3 mixes slowly: its bulk ESS per draw is far below a tenth, so a second run with
    2-4 times the draws follows, whose draws are the result."""
    import pymc as pm

    from kohpymc.sampling import sample_posterior
    from kohpymc.second_run import MAX_DRAWS_FACTOR, ess_wanted

    cov = np.array([[1.0, 0.999], [0.999, 1.0]])
    with pm.Model() as ridge:
        pm.MvNormal("z", mu=np.zeros(2), cov=cov)
    settings = dict(draws=200, tune=300, chains=2, cores=1, random_seed=3, reparameterize=False)
    idata, report = sample_posterior(ridge, sample_kwargs={"maxdepth": 3}, **settings)
    assert report.second_run, "a slowly mixing run was not sampled again"
    first_draws, second_draws = report.second_run["draws"]
    assert first_draws == 200 and 2 * 200 <= second_draws <= MAX_DRAWS_FACTOR * 200
    assert any("ESS" in r or "r_hat" in r for r in report.second_run["reasons"])
    ess = report.second_run["smallest_ess_bulk"]
    assert ess[0] < ess_wanted(2, 200) == 40.0
    assert ess[1] > ess[0]
    assert idata.posterior.sizes["draw"] == second_draws
