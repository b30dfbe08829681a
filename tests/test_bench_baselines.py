"""The benchmark baselines: numpy reference posteriors vs PyMC, RWM and surmise vs quadrature."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import kohpymc as kp  # noqa: E402
from benchmarks import baselines as bl  # noqa: E402
from kohpymc.examples import beam  # noqa: E402
from tests.reference import beam_posteriors as ref  # noqa: E402


@pytest.fixture(scope="module")
def data():
    return ref.load_beam_data()


@pytest.fixture(scope="module")
def m0_quadrature(data):
    """Posterior mean and sd of E under M0 by quadrature on a fine grid in E.

    Written independently of the baselines: scipy normal log-densities of the data under
    the library's physics function, flat prior on [50, 300].
    """
    E = np.linspace(50.0, 300.0, 250_001)
    G = beam.euler_bernoulli({"x": data.inputs["x"], "P": data.inputs["P"]}, {"E": 1.0})
    loglik = stats.norm.logpdf(data.y[None, :], G[None, :] / E[:, None], data.noise_sd).sum(1)
    w = np.exp(loglik - loglik.max())
    mean = float(np.sum(w * E) / w.sum())
    sd = float(np.sqrt(np.sum(w * (E - mean) ** 2) / w.sum()))
    return mean, sd


@pytest.mark.parametrize("label", ref.LABELS)
def test_numpy_log_posterior_equals_pymc(label, data):
    model = kp.build_model(beam.physics_model(), data, ref.beam_formulations()[label])
    post = ref.numpy_log_posterior(label, data)
    assert [v.name for v in model.value_vars] == [b.value for b in post.blocks]
    pymc_logp = model.compile_logp()
    rng = np.random.default_rng(11)
    ours, theirs = [], []
    for _ in range(6):
        vec = post.init + rng.normal(0.0, 0.5, post.ndim)
        ours.append(post.logp(vec))
        theirs.append(float(pymc_logp(post.to_point(vec))))
    ours, theirs = np.array(ours), np.array(theirs)
    assert np.all(np.isfinite(ours))
    diff = ours - theirs
    tol = 1e-8 * max(1.0, float(np.max(np.abs(theirs))))
    assert np.ptp(diff) <= tol  # equal up to a constant ...
    # ... which is zero: all normalising constants are kept (M4/M5 differ by 2.2e-8
    # because PyMC evaluates gammaln(4) of the InverseGamma length-scale prior in float32)
    assert abs(float(diff.mean())) < 1e-7


def test_white_coordinates_are_separable(data):
    full = ref.numpy_log_posterior("M4", data, white=True)
    reduced = ref.numpy_log_posterior("M4", data, white=False)
    vec = full.init + np.array([0.1, -0.2, 0.3, 0.5, -1.5])
    k = reduced.ndim
    normal = float(stats.norm.logpdf(vec[k:]).sum())
    assert full.logp(vec) == pytest.approx(reduced.logp(vec[:k]) + normal, rel=1e-12)
    assert set(reduced.to_constrained(vec[:k])) == {"E", "delta_ls", "delta_eta"}


def test_rwm_recovers_m0_quadrature_mean(data, m0_quadrature):
    mean, sd = m0_quadrature
    row, res = bl.run_baseline(
        "M0", draws=20_000, tune=3_000, chains=2, seed=3, data=data, return_result=True
    )
    assert res.idata.posterior["E"].shape == (2, 20_000)
    assert abs(row["mean_E"] - mean) < 4.0 * row["mcse_mean_E"]
    assert row["sd_E"] == pytest.approx(sd, rel=0.05)
    assert row["rhat_E"] < 1.01
    assert 0.3 < row["accept_rate"] < 0.6
    assert row["ess_per_s_E"] > 0 and row["setup_s"] > 0


def test_random_walk_metropolis_on_a_gaussian():
    cov = np.array([[1.0, 0.8], [0.8, 1.0]])
    prec = np.linalg.inv(cov)

    def logp(v):
        return -0.5 * float(v @ prec @ v)

    res = bl.random_walk_metropolis(logp, np.zeros(2), draws=20_000, tune=3_000, seed=5)
    x = res.idata.posterior["x"].values.reshape(-1, 2)
    assert np.allclose(x.mean(0), 0.0, atol=0.1)
    assert np.allclose(np.cov(x, rowvar=False), cov, atol=0.1)
    assert 0.15 < res.accept_rate < 0.35


def test_surmise_m0_posterior_mean(data, m0_quadrature):
    pytest.importorskip("surmise")
    from benchmarks.surmise_baseline import run_surmise

    mean, sd = m0_quadrature
    row = run_surmise(
        data, n_runs=60, samples=1_500, burn=300, pilots=3, pilot_samples=400, chains=1, seed=4
    )
    assert abs(row["mean_E"] - mean) < 3.0 * sd
    assert row["sd_E"] == pytest.approx(sd, rel=0.3)
    assert math.isfinite(row["ess_bulk_E"]) and row["ess_bulk_E"] > 50
