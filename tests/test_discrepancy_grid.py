"""GridGP (M4 on a full grid with replicates): exact agreement with the dense GP."""

from __future__ import annotations

import warnings

import numpy as np
import pytensor.tensor as pt
import pytest

from kohpymc import (
    CalibrationData,
    GaussianProcess,
    GridGP,
    PhysicsModel,
    Uniform,
    build_model,
    calibrate,
    predict,
)
from kohpymc.loo import loo_log_likelihood
from kohpymc.model import compose_model

SEED = 31
NOISE = 0.1
INPUTS = ["a", "b", "t"]
AXES = (np.array([0.0, 1.0]), np.array([1.0, 2.0, 3.0]), np.linspace(0.0, 1.0, 8))
REPLICATES = 3
TRUE_E = 1.5


def _physics_fn(inputs, params):
    return params["E"] * inputs["b"] * pt.exp(-inputs["t"]) + inputs["a"]


def _grid_rows(axes=AXES, replicates=REPLICATES):
    mesh = np.meshgrid(*axes, np.arange(replicates), indexing="ij")
    return {k: m.ravel() for k, m in zip(INPUTS, mesh[:-1], strict=True)}


def _truth(X):
    return TRUE_E * X["b"] * np.exp(-X["t"]) + X["a"] + 0.3 * np.sin(3.0 * X["t"]) + 0.1


@pytest.fixture(scope="module")
def physics():
    return PhysicsModel(_physics_fn, {"E": Uniform(0.5, 3.0)}, inputs=INPUTS, backend="pytensor")


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(SEED)
    X = _grid_rows()
    y = _truth(X) + rng.normal(0.0, NOISE, X["a"].size)
    perm = rng.permutation(y.size)  # rows in no particular order
    return CalibrationData({k: v[perm] for k, v in X.items()}, y[perm], noise_sd=NOISE)


def _points(model, n, seed):
    rng = np.random.default_rng(seed)
    ip = model.initial_point()
    return [{k: v + rng.normal(0.0, 0.4, np.shape(v)) for k, v in ip.items()} for _ in range(n)]


@pytest.mark.parametrize("marginalize", [True, False])
def test_log_density_and_gradient_equal_dense_gp(physics, data, marginalize):
    grid = build_model(physics, data, GridGP(INPUTS), marginalize=marginalize)
    dense = build_model(physics, data, GaussianProcess(INPUTS, mean=[]), marginalize=marginalize)
    assert {v.name for v in grid.value_vars} == {v.name for v in dense.value_vars}
    assert {"E", "delta_eta", "delta_ls"} <= set(grid.named_vars)
    lg, ld = grid.compile_logp(), dense.compile_logp()
    gg, gd = grid.compile_dlogp(), dense.compile_dlogp()
    for point in _points(dense, 3, SEED + int(marginalize)):
        np.testing.assert_allclose(lg(point), ld(point), rtol=1e-8)
        np.testing.assert_allclose(gg(point), gd(point), rtol=1e-6, atol=1e-8)


def test_zero_mean_log_density_equals_dense_numpy(physics, data):
    from scipy.stats import multivariate_normal

    model = build_model(physics, data, GridGP(INPUTS, mean="zero"))
    assert "delta_mean" not in model.named_vars
    ip = model.initial_point()
    values = {"E": 1.4, "delta_eta": 0.4, "delta_ls": np.array([1.2, 1.5, 0.3])}
    X = data.matrix(tuple(INPUTS))
    G = 1.4 * X[:, 1] * np.exp(-X[:, 2]) + X[:, 0]
    d2 = (((X[:, None, :] - X[None, :, :]) / values["delta_ls"]) ** 2).sum(-1)
    C = 0.16 * np.exp(-0.5 * d2) + (NOISE**2 + 1e-6) * np.eye(len(X))
    reference = multivariate_normal(G, C).logpdf(data.y)
    point = dict(ip, E_interval__=np.log(0.9 / 1.6), delta_eta_log__=np.log(0.4))
    point["delta_ls_log__"] = np.log(values["delta_ls"])
    y_logp = model.compile_fn(model.logp(vars=[model["y"]]), on_unused_input="ignore")
    np.testing.assert_allclose(y_logp(point), reference, rtol=1e-9)


def _numpy_conditional(data, point, X_new):
    """Dense GP conditional mean and sd (replicates as rows), integrated constant mean."""
    X = data.matrix(tuple(INPUTS))
    E, eta, ls = float(point["E"]), float(point["delta_eta"]), np.asarray(point["delta_ls"])
    G = E * X[:, 1] * np.exp(-X[:, 2]) + X[:, 0]
    G_new = E * X_new[:, 1] * np.exp(-X_new[:, 2]) + X_new[:, 0]
    c = (2.0 * float(np.std(data.y))) ** 2  # prior variance of the integrated intercept

    def k(A, B):
        d2 = ((A[:, None, :] - B[None, :, :]) / ls) ** 2
        return eta**2 * np.exp(-0.5 * d2.sum(-1)) + c

    C = k(X, X) + (NOISE**2 + 1e-6) * np.eye(len(X))
    cross = k(X_new, X)
    mean = G_new + cross @ np.linalg.solve(C, data.y - G)
    var = eta**2 + c - np.sum(cross * np.linalg.solve(C, cross.T).T, axis=1)
    return mean, np.sqrt(var + 1e-6)


def test_conditional_equals_dense_reference(physics, data):
    rng = np.random.default_rng(SEED + 5)
    new = {"a": rng.choice([0.0, 1.0], 7), "b": rng.uniform(1, 3, 7), "t": rng.uniform(0, 1.3, 7)}
    X_new = np.column_stack([new[k] for k in INPUTS])
    model = build_model(physics, data, GridGP(INPUTS), new_inputs=new)
    rv = model["gp_conditional"]
    mu, sd = rv.owner.inputs[2:4]
    needed = [model.rvs_to_values[model[k]] for k in ("E", "delta_eta", "delta_ls")]
    outs = model.replace_rvs_by_values([mu, sd])
    fn = model.compile_fn(outs, inputs=needed, on_unused_input="ignore")
    point = {"E": 1.4, "delta_eta": 0.4, "delta_ls": np.array([1.2, 1.5, 0.3])}
    values = {
        "E_interval__": np.log((1.4 - 0.5) / (3.0 - 1.4)),
        "delta_eta_log__": np.log(0.4),
        "delta_ls_log__": np.log(point["delta_ls"]),
    }
    mean, sd_val = fn(values)
    ref_mean, ref_sd = _numpy_conditional(data, point, X_new)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-8)
    np.testing.assert_allclose(sd_val, ref_sd, rtol=1e-6)


@pytest.mark.parametrize(
    "case, match",
    [
        ("off_grid", "not on a full grid"),
        ("unequal", "unequal replicates"),
        ("not_kernel", "not kernel inputs"),
        ("unknown_noise", "known noise sd"),
    ],
)
def test_clear_errors(physics, data, case, match):
    X = {k: v.copy() for k, v in data.inputs.items()}
    y = data.y.copy()
    noise = NOISE
    formulation = GridGP(INPUTS)
    if case == "off_grid":
        X["t"][0] += 0.01
    elif case == "unequal":
        X = {k: v[1:] for k, v in X.items()}
        y = y[1:]
    elif case == "not_kernel":
        formulation = GridGP(["b", "t"])
    else:
        noise = None
    bad = CalibrationData(X, y, noise_sd=noise)
    with pytest.raises(ValueError, match=match):
        build_model(physics, bad, formulation)


def test_rejects_non_constant_mean():
    with pytest.raises(ValueError, match="zero mean"):
        GridGP(INPUTS, mean=["t"])


SETTINGS = dict(draws=200, tune=200, chains=2, cores=1, random_seed=SEED, warn=False)


@pytest.fixture(scope="module")
def grid_calibration(physics, data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return calibrate(physics, data, GridGP(INPUTS), **SETTINGS)


@pytest.fixture(scope="module")
def grid_idata(grid_calibration):
    return grid_calibration.idata


def test_calibrate_and_predict_end_to_end(physics, data, grid_calibration):
    cal = grid_calibration
    idata = cal.idata
    assert idata.attrs["formulation"] == "M4"
    assert idata.log_likelihood["y"].dims == ("chain", "draw", "obs")
    assert idata.log_likelihood.attrs["pointwise"] == "loo_conditional"
    assert "delta_mean" in idata.posterior
    assert int(idata.sample_stats["diverging"].sum()) == 0
    E = idata.posterior["E"].values
    assert abs(E.mean() - TRUE_E) < 3 * E.std()  # E is identified here
    new = {"a": np.array([0.0, 1.0]), "b": np.array([1.5, 2.5]), "t": np.array([0.5, 1.1])}
    pred = predict(cal, new, random_seed=SEED)
    y_model = pred.predictions["y_model"]
    assert y_model.dims == ("chain", "draw", "pred")
    assert np.all(np.isfinite(y_model.values))


def test_pointwise_loo_equals_dense(physics, data, grid_idata):
    posterior = grid_idata.posterior.isel(draw=slice(0, 20))
    dense = compose_model(physics, data, GaussianProcess(INPUTS, mean=[]))
    reference = loo_log_likelihood(posterior, dense)["y"].values
    np.testing.assert_allclose(grid_idata.log_likelihood["y"].values[:, :20], reference, rtol=1e-7)


@pytest.mark.slow
def test_calibrate_matches_dense_gp(physics, data, grid_idata):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dense = calibrate(physics, data, GaussianProcess(INPUTS, mean=[]), **SETTINGS).idata
    e_grid, e_dense = grid_idata.posterior["E"].values, dense.posterior["E"].values
    assert abs(e_grid.mean() - e_dense.mean()) < 3 * e_dense.std()
