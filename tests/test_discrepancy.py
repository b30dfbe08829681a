"""Contract tests every formulation must pass, plus independent checks of the maths."""

import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import pytest
from scipy import integrate, optimize, stats

from kohpymc import (
    CalibrationData,
    ConstantBias,
    GaussianProcess,
    IIDGaussian,
    InputDependentGaussian,
    NoDiscrepancy,
    NonStationaryGP,
    ParametricFunction,
    build_model,
    predict,
)
from kohpymc.discrepancy import DecayingVariance
from kohpymc.examples import beam
from kohpymc.priors import Normal, Uniform

SEED = 99

FORMULATIONS = {
    "M0": lambda: NoDiscrepancy(),
    "M1": lambda: ConstantBias(),
    "M1-uniform": lambda: ConstantBias(prior=Uniform(-20, 20)),
    "M2": lambda: IIDGaussian(),
    "M3": lambda: InputDependentGaussian(mean=["x"]),
    "M3-param": lambda: InputDependentGaussian(
        mean=ParametricFunction(
            lambda v, p: p["a"] * pt.exp(-p["b"] * v["x"] / 400.0),
            {"a": Normal(0, 5), "b": Normal(0, 1)},
            inputs=["x"],
        ),
        log_variance=["x", "P"],
        link="softplus",
    ),
    "M4": lambda: GaussianProcess(["x"]),
    "M4-xP": lambda: GaussianProcess(["x", "P"]),
    "M5": lambda: NonStationaryGP(["x"], time="x"),
}


@pytest.fixture(scope="module")
def two_load_data():
    return beam.generate_data((2.5, 3.0), n_points=8, seed=SEED)


def _deterministic(model, name):
    """A deterministic as a function of a point of the value variables (as in the trace)."""
    (out,) = model.replace_rvs_by_values([model[name]])
    fn = pytensor.function(model.value_vars, out, on_unused_input="ignore")
    return lambda point: fn(*[point[v.name] for v in model.value_vars])


@pytest.mark.parametrize("label", list(FORMULATIONS))
def test_contract_logp_gradient_and_predictions(
    label, beam_physics, two_load_data, prior_calibration
):
    disc = FORMULATIONS[label]()
    model = build_model(beam_physics, two_load_data, disc)
    assert model["y"].name == "y" and model.named_vars_to_dims["y"] == ("obs",)
    point = model.initial_point()
    logp = model.compile_logp()(point)
    grad = model.compile_dlogp()(point)
    assert np.isfinite(logp) and np.all(np.isfinite(grad))
    # predictions from a small fixed set of prior draws standing in for a posterior
    fake = prior_calibration(beam_physics, two_load_data, disc, seed=SEED)
    new = beam.generate_data((3.5,), n_points=5, seed=SEED)
    pred = predict(fake, new, random_seed=SEED)
    for var in ("physics", "discrepancy", "y_model", "y_pred"):
        da = pred.predictions[var]
        assert da.dims == ("chain", "draw", "pred") and da.shape[-1] == 5
        assert np.all(np.isfinite(da.values))
    np.testing.assert_allclose(pred.predictions["x"].values, new.inputs["x"])
    np.testing.assert_allclose(pred.predictions["P"].values, 3.5)
    total = pred.predictions["physics"] + pred.predictions["discrepancy"]
    np.testing.assert_allclose(total.values, pred.predictions["y_model"].values)


def test_marginalized_constant_bias_matches_quadrature(beam_physics, two_load_data):
    """∫ N(y | G + b, σ²) N(b | 0, s²) db by quadrature == the marginal model."""
    marg = build_model(beam_physics, two_load_data, ConstantBias())
    plain = build_model(beam_physics, two_load_data, ConstantBias(), marginalize=False)
    E = 180.0
    point = marg.initial_point()
    point["E_interval__"] = np.log((E - 50) / (300 - E))
    point["delta_white"] = np.zeros(1)
    marginal = marg.compile_logp(vars=[marg["y"]])(point)

    plain_logp = plain.compile_logp(vars=[plain["y"], plain["delta"]])
    ppoint = plain.initial_point()
    ppoint["E_interval__"] = point["E_interval__"]

    def integrand(b):
        ppoint["delta"] = np.array(b)
        return np.exp(plain_logp(ppoint) - marginal)

    G = beam.euler_bernoulli(two_load_data.inputs, {"E": E})
    centre = float(np.mean(two_load_data.y - G))
    ratio, _ = integrate.quad(integrand, centre - 5, centre + 5, points=[centre], limit=200)
    assert ratio == pytest.approx(1.0, rel=1e-6)


def test_marginalized_gp_matches_grid_integration(beam_physics, two_load_data):
    """The GP with its linear-mean coefficients integrated out == 2-D grid integration."""
    disc = GaussianProcess(["x"], mean=["x"])
    marg = build_model(beam_physics, two_load_data, disc)
    plain = build_model(beam_physics, two_load_data, disc, marginalize=False)
    point = marg.initial_point()
    marginal = marg.compile_logp(vars=[marg["y"]])(point)
    plain_logp = plain.compile_logp(vars=[plain["y"], plain["delta_mean"]])
    ppoint = plain.initial_point()
    for key in ("E_interval__", "delta_ls_log__", "delta_eta_log__"):
        ppoint[key] = point[key]
    # locate the conditional mode of the coefficients, then integrate on a wide grid
    coef = _deterministic(marg, "delta_mean")(point)
    half_width = 80.0  # the conditional sds here are ~8 and ~4: the grid spans > 10 sd
    g0 = np.linspace(coef[0] - half_width, coef[0] + half_width, 241)
    g1 = np.linspace(coef[1] - half_width, coef[1] + half_width, 241)
    vals = np.empty((g0.size, g1.size))
    for i, a in enumerate(g0):
        for j, b in enumerate(g1):
            ppoint["delta_mean"] = np.array([a, b])
            vals[i, j] = plain_logp(ppoint) - marginal
    ratio = integrate.trapezoid(integrate.trapezoid(np.exp(vals), g1, axis=1), g0)
    assert ratio == pytest.approx(1.0, rel=1e-6)


def test_whitened_coefficients_have_the_exact_conditional(beam_physics, two_load_data):
    """z ~ N(0, I) mapped through the whitening gives c | θ, y: compare with the mode and
    curvature of the unmarginalized log density found numerically (optimizer + FD)."""
    disc = InputDependentGaussian(mean=["x"])
    model = build_model(beam_physics, two_load_data, disc)
    point = model.initial_point()
    f = _deterministic(model, "delta_mean")
    rng = np.random.default_rng(SEED)
    draws = np.array([f({**point, "delta_mean_white": rng.normal(size=2)}) for _ in range(4000)])
    plain = build_model(beam_physics, two_load_data, disc, marginalize=False)
    lp = plain.compile_logp(vars=[plain["y"], plain["delta_mean"]])
    pp = plain.initial_point()
    pp.update({k: v for k, v in point.items() if k in pp})

    def neg(c):
        return -lp({**pp, "delta_mean": np.asarray(c, dtype=float)})

    mode = optimize.minimize(neg, np.zeros(2), method="BFGS", options={"gtol": 1e-10}).x
    h = 1e-3
    H = np.empty((2, 2))
    for i in range(2):
        for j in range(2):
            ei, ej = np.eye(2)[i] * h, np.eye(2)[j] * h
            H[i, j] = (
                neg(mode + ei + ej)
                - neg(mode + ei - ej)
                - neg(mode - ei + ej)
                + neg(mode - ei - ej)
            ) / (4 * h * h)
    exact_cov = np.linalg.inv(H)
    se = np.sqrt(np.diag(exact_cov) / draws.shape[0])
    assert np.all(np.abs(draws.mean(axis=0) - mode) < 4 * se)
    # sample covariance of 4000 draws: relative error about sqrt(2/4000) = 2.2 %
    np.testing.assert_allclose(np.cov(draws.T), exact_cov, rtol=0.1, atol=0.02 * exact_cov.max())


def test_nonstationary_kernel_is_spd_and_reduces_to_stationary():
    rng = np.random.default_rng(SEED)
    t = np.sort(rng.uniform(0, 10, 25))
    X = np.column_stack([t, rng.normal(size=25)])
    X[5, 0] = X[4, 0]  # two rows at the same time with different second input
    se = 1.3**2 * pm.gp.cov.ExpQuad(2, ls=[2.0, 1.5])
    K5 = (se + DecayingVariance(2, w1=0.7, w2=0.3, active_dims=[0]))(X).eval()
    np.testing.assert_allclose(K5, K5.T)
    assert np.linalg.eigvalsh(K5).min() > 0
    np.linalg.cholesky(K5)
    K4 = se(X).eval()
    K5_zero = (se + DecayingVariance(2, w1=0.0, w2=0.3, active_dims=[0]))(X).eval()
    np.testing.assert_allclose(K5_zero, K4, rtol=0, atol=0)
    # the added term is w1 exp(-w2 t) exactly where t == t', zero elsewhere
    extra = K5 - K4
    same_t = X[:, 0][:, None] == X[:, 0][None, :]
    np.testing.assert_allclose(
        extra[same_t], np.broadcast_to(0.7 * np.exp(-0.3 * X[:, 0])[:, None], same_t.shape)[same_t]
    )
    assert np.all(extra[~same_t] == 0)
    assert extra[4, 5] > 0  # Eq. (14) couples rows that share t


def test_contract_errors_name_missing_inputs(beam_physics, two_load_data):
    with pytest.raises(KeyError, match=r"\['T'\].*M4.*data inputs are \['x', 'P'\]"):
        build_model(beam_physics, two_load_data, GaussianProcess(["T"]))


def test_unknown_noise_becomes_a_parameter(beam_physics):
    data = beam.generate_data(seed=SEED)
    free = CalibrationData(data.inputs, data.y)
    model = build_model(beam_physics, free, ConstantBias())
    assert "sigma_obs" in model.named_vars
    model2 = build_model(beam_physics, data, ConstantBias())
    assert "sigma_obs" not in model2.named_vars


def test_independent_likelihood_matches_scipy(beam_physics, two_load_data):
    """M2 without marginalization is N(G + μ, σ_obs² + σ_δ²) row by row."""
    model = build_model(beam_physics, two_load_data, IIDGaussian(), marginalize=False)
    point = model.initial_point()
    point["E_interval__"] = np.array(0.3)
    point["delta_sd_log__"] = np.array(np.log(0.8))
    point["delta_mean"] = np.array(1.1)
    got = model.compile_logp(vars=[model["y"]])(point)
    E = 50 + 250 / (1 + np.exp(-0.3))
    G = beam.euler_bernoulli(two_load_data.inputs, {"E": E})
    ref = stats.norm(G + 1.1, np.sqrt(two_load_data.noise_sd**2 + 0.64)).logpdf(two_load_data.y)
    assert got == pytest.approx(ref.sum(), rel=1e-10)


def test_gp_likelihood_is_not_swamped_by_jitter_on_small_outputs():
    """An output of order 1e-6 (a rate in mol/(L·s)) with noise sd 1e-8: the GP likelihood
    is the dense normal with covariance K + c 11ᵀ + (σ² + 1e-6·sd(y)²) I (the integrated
    intercept's prior variance c = (2 sd(y))²).  PyMC's absolute jitter 1e-6 (an sd of
    1e-3, 10⁵ times the noise) made the data uninformative."""
    from kohpymc import PhysicsModel

    rng = np.random.default_rng(SEED)
    x = np.linspace(0.0, 1.0, 12)
    y = 2e-6 * x + 1e-7 * np.sin(6.0 * x) + rng.normal(0.0, 1e-8, x.size)
    physics = PhysicsModel(
        lambda inputs, p: p["E"] * inputs["x"], {"E": Uniform(1e-6, 4e-6)}, inputs=["x"],
        backend="pytensor",
    )  # fmt: skip
    data = CalibrationData({"x": x}, y, noise_sd=1e-8)
    model = build_model(physics, data, GaussianProcess(["x"], mean=[]))
    E, eta, ls = 2e-6, 1e-7, 0.3
    sd_y = float(np.std(y))
    K = eta**2 * np.exp(-0.5 * (x[:, None] - x[None, :]) ** 2 / ls**2) + (2 * sd_y) ** 2
    C = K + (1e-8**2 + 1e-6 * sd_y**2) * np.eye(x.size)
    reference = stats.multivariate_normal(E * x, C).logpdf(y)
    point = dict(model.initial_point(), E_interval__=np.log(1.0 / 2.0))
    point.update(delta_eta_log__=np.log(eta), delta_ls_log__=np.log([ls]))
    y_logp = model.compile_logp(vars=[model["y"]])
    np.testing.assert_allclose(y_logp(point), reference, rtol=1e-9)
