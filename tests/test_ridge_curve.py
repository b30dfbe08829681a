"""The ridge-curve plan's pivot warp on a ridge the data bound on one side only."""

import arviz as az
import numpy as np
import pymc as pm
import pytest
from scipy import stats
from scipy.special import expit, logit

from kohpymc.priors import _log_uniform
from kohpymc.reparameterization import plan
from kohpymc.ridge_curve import _nodes, _pivot_warp
from kohpymc.sampling import sample_posterior
from kohpymc.value_space import value_space

SEED = 15
#: substrate concentrations (M), each measured twice, mostly below K_m = 1e-4
_S = np.repeat(np.array([2, 3, 5, 7, 10, 12, 15, 20, 25, 30, 40, 50, 70, 100, 150]) * 1e-6, 2)
_SD = 3e-10  # M/s, the noise sd (known here)


def test_warp_matches_the_quantiles_of_a_skewed_marginal():
    """A Gumbel marginal in ``w`` (a double-exponential wall on one side, as ``ln K_i``'s):
    the warp maps standard-normal quantiles onto its quantiles, ``−ln(−ln Φ(t))``."""
    nodes = _nodes(101)
    w = logit(nodes)
    warp = _pivot_warp(nodes, -(w + np.exp(-w)))
    t = np.linspace(-3.0, 3.0, 13)
    np.testing.assert_allclose(warp(t), -np.log(-np.log(stats.norm.cdf(t))), atol=0.01)


def _inhibition_data() -> np.ndarray:
    rng = np.random.default_rng(SEED)
    return 1e-6 * _S / (1e-4 + _S + _S**2 / 3e-2) + rng.normal(0.0, _SD, _S.size)


def _inhibition_model(y: np.ndarray) -> pm.Model:
    """Substrate inhibition ``v = V S / (K_m + S + S²/K_i)``, log-uniform priors in natural
    units: the data fix ``V`` and ``K_m`` and bound ``K_i`` from below only."""
    with pm.Model() as model:
        vmax = _log_uniform("Vmax", 1e-8, 1e-4)
        km = _log_uniform("Km", 1e-6, 1e-2)
        ki = _log_uniform("Ki", 1e-4, 1.0)
        pm.Normal("y", vmax * _S / (km + _S + _S**2 / ki), _SD, observed=y)
    return model


def _inhibition_reference(y: np.ndarray, centre_km: float) -> dict[str, tuple[float, float]]:
    """Mean and sd of ``ln V``, ``ln K_m``, ``ln K_i`` by quadrature.

    On a grid of ``(ln K_m, ln K_i)``, ``V`` (linear in the model, 1/V prior) is integrated
    by its Gaussian conditional: ``∝ e^{−RSS/2σ²} σ_V / V̂`` (its relative sd is 0.3 %).
    """
    lki = np.linspace(np.log(1e-4), 0.0, 601)
    lkm = centre_km + np.linspace(-0.03, 0.03, 401)
    g = _S / (np.exp(lkm)[:, None, None] + _S + _S**2 / np.exp(lki)[None, :, None])
    gg = (g * g).sum(-1)
    vhat = (g * y).sum(-1) / gg
    rss = ((y - vhat[..., None] * g) ** 2).sum(-1)
    log_weight = -0.5 * rss / _SD**2 - 0.5 * np.log(gg) - np.log(vhat)
    weight = np.exp(log_weight - log_weight.max())
    weight /= weight.sum()
    moments = {}
    for name, value in (("Vmax", np.log(vhat)), ("Km", lkm[:, None]), ("Ki", lki[None, :])):
        mean = float((weight * value).sum())
        moments[name] = (mean, float(np.sqrt((weight * (value - mean) ** 2).sum())))
    return moments


def test_one_sided_ridge_is_followed_with_a_warped_pivot():
    """The best Laplace map scores 3.3 (``K_i``'s marginal is a plateau up to its upper bound
    with a wall below); its pivot's marginal sd is only 5× its conditional sd at the mode,
    under the ridge curve's 10, so it was not followed.  Now followed, its pivot warped to
    normal quantiles: the log density along every axis within 0.05 of a Gaussian's at ±1.5,
    and the map's gradient and round trip exact."""
    space = value_space(_inhibition_model(_inhibition_data()))
    chosen = plan(space, seed=SEED)
    assert chosen.kind == "ridge-curve-soft-box-warped", chosen.reason
    assert chosen.gaussian_score < 0.05
    z = np.random.default_rng(SEED).normal(size=space.ndim)
    _, grad = chosen.logp_dlogp(space, z)
    step = 1e-6
    numeric = [
        (chosen.logp_dlogp(space, z + step * e)[0] - chosen.logp_dlogp(space, z - step * e)[0])
        / (2 * step)
        for e in np.eye(space.ndim)
    ]
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(chosen.from_value(chosen.to_value(z)), z, atol=1e-9)
    assert 0.0 < expit(chosen._pivot_of(0.0)[0]) < 1.0


def test_draws_along_a_one_sided_ridge_match_quadrature():
    """2 × (1000 + 1000) draws: before (a parabola bent on the Laplace map, score 0.27) r̂
    1.02, bulk ESS 188–241, ln K_i's sd 10 % short; now no divergence, r̂ ≤ 1.01, bulk ESS
    ≥ 800, and the means and sds of ln V, ln K_m, ln K_i within 4 Monte Carlo errors of
    quadrature."""
    y = _inhibition_data()
    idata, report = sample_posterior(
        _inhibition_model(y), draws=1000, tune=1000, chains=2, random_seed=1
    )
    assert report.reparameterization["kind"] == "ridge-curve-soft-box-warped"
    assert int(idata.sample_stats.diverging.sum()) == 0
    assert float(az.rhat(idata).to_array().max()) <= 1.01
    ess = az.ess(idata)
    centre_km = float(np.median(np.log(idata.posterior["Km"].values)))
    for name, (mean, sd) in _inhibition_reference(y, centre_km).items():
        draws = np.log(idata.posterior[name].values.ravel())
        n_eff = float(ess[name])
        assert n_eff >= 800, (name, n_eff)
        assert abs(draws.mean() - mean) < 4 * sd / np.sqrt(n_eff), (name, draws.mean(), mean)
        assert abs(draws.std(ddof=1) / sd - 1) < 4 / np.sqrt(2 * n_eff), (name, draws.std(), sd)


def test_ridge_members_are_log_scale_elements_only():
    """Two interval elements on a ridge (correlation 0.999) and an uninformed third element.

    The precision's flattest direction is the third element's alone (sd 1e3): its
    log-scale part is zero, so every element passed ``d >= 0.1 * d[pivot]`` and became a
    member, the third one (no bounds: NaN box) too; from_value then gave NaN
    ("invalid value encountered in logaddexp" on a Paris-law crack study's M3).
    """
    from types import SimpleNamespace

    from kohpymc.ridge_curve import _ridge_members

    cov = np.zeros((3, 3))
    cov[:2, :2] = [[1.0, 0.999], [0.999, 1.0]]
    cov[2, 2] = 1e6
    coords = SimpleNamespace(log_scale=np.array([True, True, False]), walls=False, ridge=None)
    laplace = SimpleNamespace(coordinates=coords, chol=np.linalg.cholesky(cov))
    assert _ridge_members(laplace) is None
    # with the third element informed, the ridge is the first two's
    cov[2, 2] = 1e-2
    laplace = SimpleNamespace(coordinates=coords, chol=np.linalg.cholesky(cov))
    pivot, members = _ridge_members(laplace)
    assert pivot in (0, 1) and members.tolist() == [0, 1]


@pytest.mark.slow
def test_thermistor_gp_pivot_is_warped_past_its_wall():
    """Steinhart–Hart under a stationary GP discrepancy (M4): the ridge is led by C in its
    own units, and below C ≈ −10⁻⁷, where the GP must take up the physics' misfit, the
    posterior ends in a wall (affine pivot: log density 20.6 down at −2, 2.4 at +2; a
    Gaussian's 2.0; bent on top, 85 divergent transitions in 4 × 1000 draws).  Warped to
    its marginal's quantiles, the pivot's axis drops within 0.5 of a Gaussian's at ±2 and
    within 1.5 at ±4 (measured 2.0 and 8.0 on both sides; 21 divergences)."""
    from kohpymc.discrepancy import GaussianProcess
    from kohpymc.model import compose_model
    from kohpymc.reparameterization import _axis_drops
    from tests.test_reparameterization import _thermistor_case

    physics, data = _thermistor_case()
    space = value_space(compose_model(physics, data, GaussianProcess(["R"])).model)
    chosen = plan(space, seed=3)
    assert chosen.kind == "ridge-curve-own-units-soft-box-warped", chosen.reason
    np.testing.assert_allclose(_axis_drops(space, chosen, 2.0)[0], 2.0, atol=0.5)
    np.testing.assert_allclose(_axis_drops(space, chosen, 4.0)[0], 8.0, atol=1.5)
