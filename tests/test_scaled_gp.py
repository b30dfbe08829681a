"""M6, the scaled GP (S-GaSP): its covariance against independent dense computations,
its limit (λ_z → 0 is M4), the plain (TOML) form, and the issue's acceptance test (θ
pulled towards the L2-best value, calibrated predictive bands)."""

import arviz as az
import numpy as np
import pymc as pm
import pytest

import kohpymc as kp
from kohpymc.discrepancy import GaussianProcess, ScaledGP
from kohpymc.discrepancy.base import formulation_class, from_dict
from kohpymc.discrepancy.scaled_gp import SGaSPCovariance
from kohpymc.model import compose_model
from kohpymc.priors import HalfNormal, LogNormal

SEED = 614


def _se(X, Xs, eta, ls):
    d = X[:, None, 0] - Xs[None, :, 0]
    return eta**2 * np.exp(-0.5 * d**2 / ls**2)


def _line():
    """``G(x; θ) = θ x`` with θ ~ U(0, 3)."""
    return kp.PhysicsModel(
        lambda i, p: p["theta"] * i["x"], {"theta": kp.Uniform(0, 3)}, ["x"], backend="pytensor"
    )


# ---------------------------------------------------------------- covariance (a)
def test_covariance_is_the_penalised_gaussian_on_the_joint_points():
    """``k_z`` on calibration ∪ new points = the GP prior times exp(-λ_z Σ δ(x_i)² / 2nσ²)
    over the calibration points only (precision form, dense numpy inverses)."""
    rng = np.random.default_rng(SEED)
    X = np.sort(rng.uniform(0, 1, 6))[:, None]
    Xs = rng.uniform(0, 1, 3)[:, None]
    eta, ls, lam = 0.7, 0.25, 40.0
    n = len(X)
    c = n * eta**2 / lam
    cov = SGaSPCovariance(eta**2 * pm.gp.cov.ExpQuad(1, ls=ls), X, c)
    allX = np.vstack([X, Xs])
    precision = np.linalg.inv(_se(allX, allX, eta, ls))
    precision[:n, :n] += np.eye(n) * lam / (n * eta**2)
    reference = np.linalg.inv(precision)
    np.testing.assert_allclose(cov(allX).eval(), reference, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(cov(X, Xs).eval(), reference[:n, n:], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(cov(Xs, diag=True).eval(), np.diag(reference)[n:], rtol=1e-7)


def test_covariance_matches_brute_force_monte_carlo():
    """Reweighting GaSP draws by the discretised ``p_Z`` gives the S-GaSP covariance."""
    rng = np.random.default_rng(SEED)
    X = np.linspace(0, 1, 5)[:, None]
    eta, ls, lam = 1.0, 0.3, 10.0
    n = len(X)
    draws = rng.multivariate_normal(np.zeros(n), _se(X, X, eta, ls), size=400_000)
    w = np.exp(-lam / (2 * n * eta**2) * np.sum(draws**2, axis=1))
    w /= w.sum()
    mc = (draws * w[:, None]).T @ draws
    exact = SGaSPCovariance(eta**2 * pm.gp.cov.ExpQuad(1, ls=ls), X, n * eta**2 / lam)(X).eval()
    np.testing.assert_allclose(mc, exact, atol=0.01)
    assert np.trace(exact) < 0.7 * n * eta**2  # a real shrinkage at this λ_z


def _record_covariance(disc, data, point):
    built = compose_model(_line(), data, disc)
    fn, names = built.natural_function([built.likelihood.covariance])
    return fn(*[point[k] for k in names])[0], built


@pytest.fixture(scope="module")
def small_data():
    rng = np.random.default_rng(SEED)
    x = np.sort(rng.uniform(0, 1, 7))
    return kp.CalibrationData({"x": x}, 1.3 * x + 0.2 * np.sin(6 * x), noise_sd=0.05)


def test_likelihood_covariance_with_the_default_lambda_z(small_data):
    """Record covariance = K_z + σ² I (+ M4's jitter, 1e-6·sd(y)² here: sd(y) < 1), λ_z from
    RobustCalibration's rule."""
    point = {"theta": 1.0, "delta_eta": 0.4, "delta_ls": np.array([0.3])}
    got, built = _record_covariance(ScaledGP(["x"]), small_data, point)
    assert "delta_lambda_z" in built.formulation_variables
    X = small_data.matrix(["x"])
    n, span, sd = len(X), np.ptp(X), 0.05
    beta = 1 / (np.sqrt(2) * 0.3)  # exp(-(β d)²) form of the SE kernel
    lam = np.sqrt(n * beta * span * 0.4**2 / sd**2)
    K = _se(X, X, 0.4, 0.3)
    expected = np.linalg.inv(np.linalg.inv(K) + lam / (n * 0.4**2) * np.eye(n))
    jitter = 1e-6 * min(1.0, float(np.std(small_data.y)) ** 2)
    np.testing.assert_allclose(got, expected + (sd**2 + jitter) * np.eye(n), rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("lam", [0.0, 1e-10])
def test_zero_lambda_z_is_the_gasp_of_m4(small_data, lam):
    point = {"theta": 1.0, "delta_eta": 0.4, "delta_ls": np.array([0.3]), "delta_mean_white": 0}
    m4, _ = _record_covariance(GaussianProcess(["x"]), small_data, point)
    m6, _ = _record_covariance(ScaledGP(["x"], mean=["x"], lambda_z=lam), small_data, point)
    np.testing.assert_allclose(m6, m4, rtol=1e-8, atol=1e-10)


def test_logp_gradient_and_prediction_at_new_inputs(small_data):
    built = compose_model(
        _line(),
        small_data,
        ScaledGP(["x"], lambda_z=LogNormal(3.0, 1.0)),
        new_inputs={"x": [0.1, 0.5]},
    )
    model = built.model
    point = model.initial_point()
    assert np.isfinite(model.compile_logp()(point))
    assert np.all(np.isfinite(model.compile_dlogp()(point)))
    assert model.named_vars_to_dims["y_model"] == ("pred",)
    assert "delta_lambda_z" in [rv.name for rv in model.free_RVs]


# ---------------------------------------------------------------- plain form (c)
def test_plain_form_round_trip():
    assert formulation_class("scaled_gp") is ScaledGP
    m6 = from_dict({"type": "scaled_gp"}, inputs=["x"])
    assert isinstance(m6, ScaledGP) and m6.inputs == ("x",) and m6.label == "M6"
    assert m6.to_dict() == {"type": "scaled_gp", "inputs": ["x"]}
    full = ScaledGP(
        ["x", "P"],
        mean=["x"],
        amplitude_prior=HalfNormal(2.0),
        lambda_z={"prior": "lognormal", "mu": 3.0, "sigma": 1.0},
    )
    spec = full.to_dict()
    back = from_dict(spec)
    assert back.to_dict() == spec and back.inputs == ("x", "P")
    assert from_dict({"type": "scaled_gp", "lambda_z": 5.0}, inputs=["x"]).lambda_z == 5.0
    with pytest.raises(kp.discrepancy.base.FormulationSpecError, match="lambda_z"):
        from_dict({"type": "scaled_gp", "lambda_z": -1.0}, inputs=["x"])


# ---------------------------------------------------------------- acceptance (b)
#: truth ζ(x) = a x + b sin(2πx) on [0, 1]; physics G = θ x;
#: θ* = argmin ∫ (ζ - θ x)² dx = 3 ∫ x ζ dx = a - 3b / (2π)
A, B, NOISE = 1.5, 0.4, 0.05
THETA_STAR = A - 3 * B / (2 * np.pi)


def _truth(x):
    return A * x + B * np.sin(2 * np.pi * x)


def _acceptance(draws):
    rng = np.random.default_rng(7)
    x = np.sort(rng.uniform(0, 1, 25))
    data = kp.CalibrationData({"x": x}, _truth(x) + rng.normal(0, NOISE, 25), noise_sd=NOISE)
    x_new = rng.uniform(0, 1, 40)
    y_new = _truth(x_new) + rng.normal(0, NOISE, 40)
    out = {}
    for label, disc in (("M4", GaussianProcess(["x"])), ("M6", ScaledGP(["x"]))):
        cal = kp.calibrate(
            _line(), data, disc, draws=draws, tune=draws, chains=2, cores=2,
            random_seed=3, warn=False,
        )  # fmt: skip
        theta = cal.idata.posterior["theta"]
        y_pred = cal.predict({"x": x_new}, random_seed=1).predictions["y_pred"]
        lo, hi = y_pred.quantile([0.05, 0.95], dim=("chain", "draw")).values
        out[label] = {
            "mean": float(theta.mean()),
            "sd": float(theta.std()),
            "coverage": float(np.mean((y_new >= lo) & (y_new <= hi))),
            "r_hat": float(az.rhat(cal.idata)["theta"]),
            "divergences": int(cal.idata.sample_stats.diverging.sum()),
        }
    return out


def _check(out):
    m4, m6 = out["M4"], out["M6"]
    assert abs(m6["mean"] - THETA_STAR) < abs(m4["mean"] - THETA_STAR), out
    assert abs(m6["mean"] - THETA_STAR) < 2 * m6["sd"], out  # k = 2
    assert 0.80 <= m6["coverage"] <= 1.0, out
    assert m6["r_hat"] < 1.02 and m6["divergences"] == 0, out


def test_sgasp_pulls_theta_to_the_l2_best_value():
    """The issue's acceptance test at small size (300 + 300 draws, 2 chains)."""
    _check(_acceptance(300))


@pytest.mark.slow
def test_sgasp_pulls_theta_to_the_l2_best_value_full():
    _check(_acceptance(1000))
