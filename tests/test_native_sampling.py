"""Nutpie's native path: the symbolic z -> v map is the numpy one, and its draws are right."""

import json

import arviz as az
import numpy as np
import pymc as pm
import pytensor
import pytest

import kohpymc.native as native
from kohpymc.native import density_in_z, parameters, python_only_ops, symbolic_value
from kohpymc.reparameterization import (
    BoundRidge,
    Coordinates,
    Reparameterization,
    log_coordinates,
)
from kohpymc.sampling import sample_posterior, variance_shares
from kohpymc.value_space import value_space

SEED = 20261125


def _model():
    """Two positive interval parameters, two sds of which only a² + b² is informed, a slope."""
    rng = np.random.default_rng(SEED)
    x = np.linspace(1.0, 2.0, 12)
    y = 0.8 * 1.5 * x + rng.normal(0.0, 0.3, x.size)
    with pm.Model() as model:
        m = pm.Uniform("m", 0.5, 3.0)
        phi = pm.Uniform("phi", 1.0, 2.0)
        a = pm.HalfNormal("a", 1.0)
        b = pm.HalfNormal("b", 1.0)
        c = pm.Normal("c", 0.0, 1.0)
        pm.Normal("y", m * phi * x + c, pm.math.sqrt(a**2 + b**2), observed=y)
    return model


def _plan(space, coords, kind):
    """A plan with a fixed, arbitrary (not fitted) mean and lower-triangular factor."""
    rng = np.random.default_rng(SEED)
    mean = coords.from_value(np.array([0.2, -0.3, -1.0, -1.5, 0.1]))
    chol = np.tril(rng.normal(0.0, 0.1, (space.ndim, space.ndim)), -1) + np.diag(
        rng.uniform(0.2, 0.5, space.ndim)
    )
    return Reparameterization(kind, mean, chol, coords, "")


def _coordinates(space, kind):
    shares = variance_shares(space, [("a", "b")])
    if kind == "affine":
        return Coordinates.identity(space.ndim)
    if kind == "log-logit":
        return log_coordinates(space)
    if kind == "walls":
        return log_coordinates(space, walls=True)
    if kind == "shares":
        return log_coordinates(space).with_shares(shares)
    # bound ridge: m (index 0) regressed out of the others, with the shares and log-logit
    coords = log_coordinates(space).with_shares(shares)
    cov = np.full((space.ndim, space.ndim), 0.02) + np.diag(np.full(space.ndim, 0.1))
    mean = coords.from_value(np.array([0.2, -0.3, -1.0, -1.5, 0.1]))
    bounds = (space.lower[[0]], space.upper[[0]])
    ridge = BoundRidge.fit(coords, mean, cov, np.array([0]), bounds)
    return coords.with_ridge(ridge)


KINDS = ["affine", "log-logit", "walls", "shares", "bound-ridge", "bent", "squeezed-bent"]


def _bent(plan, kind):
    """``plan`` with an arbitrary (not fitted) bend of axis 1 and, for "squeezed-bent", a
    squeeze of axis 3: unit-triangular as :func:`kohpymc.bends.bend_plan` builds it."""
    from kohpymc.bends import Bend, BentPlan, Squeeze

    inverse = np.linalg.inv(plan.chol)
    coefs = np.array([[0.3], [0.0], [-0.2], [0.1], [0.25]])  # zero on the bent axis
    bend = Bend(plan.mean.copy(), inverse[[1]], plan.chol @ coefs)
    squeeze = None
    if kind == "squeezed-bent":
        squeeze = Squeeze(plan.mean.copy(), inverse[[3]], plan.chol[:, [3]], np.array([0.4]))
    return BentPlan(kind, plan.mean, plan.chol, plan.coordinates, "", bend=bend, squeeze=squeeze)


def _any_plan(space, kind):
    """:func:`_plan` in the coordinates of ``kind``, bent for the bent kinds."""
    if kind.endswith("bent"):
        return _bent(_plan(space, _coordinates(space, "shares"), kind), kind)
    return _plan(space, _coordinates(space, kind), kind)


@pytest.fixture(scope="module")
def space():
    return value_space(_model())


@pytest.mark.parametrize("kind", KINDS)
def test_symbolic_map_and_density_equal_the_numpy_ones(space, kind):
    """v(z), log p(v(z)) + log|dv/dz| and its gradient: PyTensor graph against the numpy map
    and Reparameterization.logp_dlogp, to 1e-10 relative, at three points around the mean.
    The bent plans' bend and squeeze enter through θ, not as constants of the graph."""
    plan = _any_plan(space, kind)
    z_var, theta, logp, grad, shared = density_in_z(space, plan)
    density = pytensor.function([z_var, theta], [logp, grad])
    value = pytensor.function([z_var], symbolic_value(plan, z_var)[0])
    rng = np.random.default_rng(SEED)
    for z in rng.normal(0.0, 0.7, (3, space.ndim)):
        np.testing.assert_allclose(value(z), plan.to_value(z), rtol=1e-10, atol=1e-12)
        expected_logp, expected_grad = plan.logp_dlogp(space, z)
        got_logp, got_grad = density(z, parameters(plan, shared))
        assert got_logp == pytest.approx(expected_logp, rel=1e-10, abs=1e-10)
        scale = np.max(np.abs(expected_grad))
        np.testing.assert_allclose(got_grad, expected_grad, rtol=1e-10, atol=1e-10 * scale)


def test_native_c_function_equals_the_numpy_density(space):
    """The C function nutpie calls (the graph's numba function inlined into it), called
    through ctypes with θ as user data: the numpy map's log density and gradient."""
    import ctypes

    plan = _plan(space, _coordinates(space, "shares"), "shares")
    z_var, theta, logp, grad, shared = density_in_z(space, plan)
    function = pm.pytensorf.compile([z_var, theta], [logp, grad], mode="NUMBA")
    n = space.ndim
    logp_c = native._logp_cfunc(function.vm.jit_fn, n, int(theta.type.shape[0]))
    user_data = parameters(plan, shared)
    rng = np.random.default_rng(SEED)
    for z in rng.normal(0.0, 0.7, (3, n)):
        z = np.ascontiguousarray(z)
        out, value = np.zeros(n), np.zeros(())
        code = logp_c.ctypes(
            n, z.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
            out.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
            value.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
            user_data.ctypes.data_as(ctypes.c_void_p),
        )  # fmt: skip
        assert code == 0
        expected_logp, expected_grad = plan.logp_dlogp(space, z)
        assert float(value) == pytest.approx(expected_logp, rel=1e-10, abs=1e-10)
        scale = np.max(np.abs(expected_grad))
        np.testing.assert_allclose(out, expected_grad, rtol=1e-10, atol=1e-10 * scale)


def _call_c(logp_c, z, user_data):
    """Nutpie's call of a log-density C function: (code, logp, gradient)."""
    import ctypes

    z = np.ascontiguousarray(z)
    out, value = np.zeros(z.size), np.zeros(())
    code = logp_c.ctypes(
        z.size, z.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
        out.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
        value.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
        user_data.ctypes.data_as(ctypes.c_void_p),
    )  # fmt: skip
    return code, float(value), out


def _numba_model():
    """:func:`_model` with a second likelihood term on shared data (as an emulator's
    matrices), and its NUMBA value space."""
    rng = np.random.default_rng(SEED + 1)
    y_obs = pytensor.shared(rng.normal(1.0, 0.5, 12), name="y_obs")
    model = _model()
    with model:
        pm.Normal("y2", model["c"], model["a"] + 1.0, observed=y_obs)
    return model, value_space(model, mode="NUMBA")


#: plans whose whole map is user data of one shared C function (native._affine_logp_c)
PLAIN_KINDS = ["affine", "log-logit", "walls", "shares"]


@pytest.mark.parametrize("kind", [*PLAIN_KINDS, "bound-ridge", "squeezed-bent"])
def test_native_model_reuses_the_compiled_density_and_equals_the_numpy_one(kind):
    """A NUMBA space: nutpie's C function is the map z -> v around the space's compiled
    density (the model's graph is not compiled again), with shared data read from the
    user data; its log density and gradient are the numpy map's (1e-10 relative).
    Plain plans all share one C function; the others compile their own map."""
    rng = np.random.default_rng(SEED)
    model, space = _numba_model()
    plan = _any_plan(space, kind)
    composed = native._composed_logp(space, plan)
    assert composed is not None
    logp_c, _, user_data = composed
    assert (logp_c is native._affine_logp_c()) == (kind in PLAIN_KINDS)
    for z in rng.normal(0.0, 0.7, (3, space.ndim)):
        code, value, grad = _call_c(logp_c, z, user_data)
        expected_logp, expected_grad = plan.logp_dlogp(space, z)
        assert code == 0 and value == pytest.approx(expected_logp, rel=1e-10, abs=1e-10)
        scale = np.max(np.abs(expected_grad))
        np.testing.assert_allclose(grad, expected_grad, rtol=1e-10, atol=1e-10 * scale)
    # the C space has no compiled numba density to reuse: the whole density is compiled
    assert native._composed_logp(value_space(model), plan) is None


def test_one_c_function_serves_plain_plans_of_every_dimension():
    """The shared C function of plain plans evaluates a 1-D and a 5-D model alike (numpy
    map's density to 1e-10), and outside a wall returns nutpie's code for a non-finite
    density without calling the density."""
    with pm.Model() as small:
        k = pm.LogNormal("k", 0.0, 1.0)
        pm.Normal("y", k * np.arange(1.0, 4.0), 0.2, observed=[1.1, 1.9, 3.2])
    _, big = _numba_model()
    rng = np.random.default_rng(SEED)
    one = Reparameterization("affine", np.array([0.1]), np.array([[0.3]]),
                             Coordinates.identity(1), "")  # fmt: skip
    for space, plan in [(value_space(small, mode="NUMBA"), one), (big, _any_plan(big, "shares"))]:
        logp_c, _, user_data = native._composed_logp(space, plan)
        assert logp_c is native._affine_logp_c()
        for z in rng.normal(0.0, 0.7, (2, space.ndim)):
            code, value, grad = _call_c(logp_c, z, user_data)
            expected_logp, expected_grad = plan.logp_dlogp(space, z)
            assert code == 0 and value == pytest.approx(expected_logp, rel=1e-10, abs=1e-10)
            np.testing.assert_allclose(grad, expected_grad, rtol=1e-9, atol=1e-12)
    plan = _plan(big, _coordinates(big, "walls"), "walls")
    w = plan.mean.copy()
    w[1] = np.log(big.upper[1]) + 0.1  # phi beyond its upper bound
    outside = np.linalg.solve(plan.chol, w - plan.mean)
    logp_c, _, user_data = native._composed_logp(big, plan)
    assert _call_c(logp_c, outside, user_data)[0] == 4  # non-finite density: rejected


def test_symbolic_map_outside_the_walls_has_zero_density(space):
    """Log-scale coordinates with walls: a point beyond ln b has log density -inf, as in numpy."""
    plan = _plan(space, _coordinates(space, "walls"), "walls")
    z = plan.from_value(plan.to_value(np.zeros(space.ndim)))
    z_var, theta, logp, grad, shared = density_in_z(space, plan)
    density = pytensor.function([z_var, theta], [logp, grad])
    w = plan.mean + plan.chol @ z
    w[1] = np.log(space.upper[1]) + 0.1  # phi beyond its upper bound
    outside = np.linalg.solve(plan.chol, w - plan.mean)
    assert plan.logp_dlogp(space, outside)[0] == -np.inf
    got_logp, got_grad = density(outside, parameters(plan, shared))
    assert got_logp == -np.inf
    assert np.all(np.isfinite(got_grad))


def test_shared_data_enter_as_parameters_not_constants():
    """Observed data in a shared variable (swapped per replicate by the SBC check): its values
    are read from θ, so the density follows set_value and the compiled graph does not change."""
    rng = np.random.default_rng(SEED)
    with pm.Model() as model:
        y = pytensor.shared(rng.normal(1.0, 0.5, 8), name="y_obs")
        mu = pm.Normal("mu", 0.0, 5.0)
        sigma = pm.HalfNormal("sigma", 1.0)
        pm.Normal("y", mu, sigma, observed=y)
    space = value_space(model)
    plan = _plan_for(space)
    z_var, theta, logp, grad, shared = density_in_z(space, plan)
    assert [var.name for var in shared] == ["y_obs"]
    density = pytensor.function([z_var, theta], [logp, grad])
    z = np.array([0.4, -0.2])
    for values in (rng.normal(1.0, 0.5, 8), rng.normal(-2.0, 0.1, 8)):
        y.set_value(values)
        expected_logp, expected_grad = plan.logp_dlogp(space, z)
        got_logp, got_grad = density(z, parameters(plan, shared))
        assert got_logp == pytest.approx(expected_logp, rel=1e-10)
        np.testing.assert_allclose(got_grad, expected_grad, rtol=1e-10)


def _plan_for(space):
    chol = np.array([[0.3, 0.0], [0.05, 0.2]])
    return Reparameterization("affine", np.array([1.0, -0.5]), chol, Coordinates.identity(2), "")


def test_correlated_gaussian_sampled_natively_matches_its_moments():
    """Correlation 0.9999, scales 1e-5 and 1e5, pure PyTensor: the native path runs on two
    threads, and the draws' mean, sds (4 Monte Carlo errors from the bulk ESS) and correlation
    (Fisher z, 4 errors) match the exact ones."""
    mean = np.array([3e-5, -2e5])
    sd = np.array([1e-5, 1e5])
    rho = 0.9999
    cov = np.array([[sd[0] ** 2, rho * sd[0] * sd[1]], [rho * sd[0] * sd[1], sd[1] ** 2]])
    with pm.Model(coords={"param": ["small", "large"]}) as model:
        pm.MvNormal("theta", mu=mean, cov=cov, dims="param")
    idata, report = sample_posterior(model, draws=1000, tune=500, chains=4, random_seed=SEED)
    assert report.nutpie_backend == "numba-native"
    assert report.chain_threads == 2
    assert report.reparameterization["kind"] == "affine"
    assert int(idata.sample_stats.diverging.sum()) == 0
    assert idata.posterior["theta"].dims == ("chain", "draw", "param")
    assert list(idata.posterior["param"].values) == ["small", "large"]
    draws = idata.posterior["theta"].values.reshape(-1, 2)
    ess = float(az.ess(idata, var_names=["theta"])["theta"].min())
    assert ess > 800
    assert np.all(np.abs(draws.mean(axis=0) - mean) < 4 * sd / np.sqrt(ess))
    assert np.all(np.abs(draws.std(axis=0, ddof=1) / sd - 1) < 4 / np.sqrt(2 * ess))
    r = np.corrcoef(draws.T)[0, 1]
    assert abs(np.arctanh(r) - np.arctanh(rho)) < 4 / np.sqrt(ess)


def _structured_model():
    with pm.Model(coords={"param": ["a", "b"]}) as model:
        theta = pm.Normal("theta", 0.0, 1.0, dims="param")
        s = pm.HalfNormal("s", 1.0)
        w = pm.Normal("w", 0.0, 1.0, shape=3)
        pm.Deterministic("d", theta.sum() * s)
        pm.Deterministic("e", 2.0 * w)
        # linear in theta and w: the bilinear theta[1]·Σw that was here is a curved ridge
        # that plan() now follows (bends.follow_plan, a map with no symbolic form), and
        # this test needs a map both paths run; 30 rows, not 2: with s unknown, 2 rows make
        # a funnel that the noise-funnel map (no symbolic form either) takes on
        observed = np.random.default_rng(SEED).normal(0.2, 0.3, 30)
        pm.Normal("y", theta[0] + 0.5 * theta[1] + w.sum(), s, observed=observed)
    return model


def test_native_and_python_paths_give_the_same_inferencedata(monkeypatch):
    """Same variables, dims, coords and groups; the same draws up to the floating-point
    differences of the two log densities (identical here: seeds and map agree)."""
    native_idata, native_report = sample_posterior(
        _structured_model(), draws=100, tune=100, chains=2, random_seed=SEED
    )
    assert native_report.nutpie_backend == "numba-native"

    def fail(*args, **kwargs):
        raise RuntimeError("switched off by the test")

    monkeypatch.setattr(native, "native_model", fail)
    python_idata, python_report = sample_posterior(
        _structured_model(), draws=100, tune=100, chains=2, random_seed=SEED
    )
    assert python_report.nutpie_backend == (
        "python (native: RuntimeError: switched off by the test)"
    )
    assert python_report.chain_threads == 1
    assert native_idata.groups() == python_idata.groups()
    a, b = native_idata.posterior, python_idata.posterior
    assert set(a.data_vars) == set(b.data_vars) == {"theta", "s", "w", "d", "e"}
    assert dict(a.sizes) == dict(b.sizes)
    for name in b.data_vars:
        assert a[name].dims == b[name].dims, name
    for name in b.coords:
        np.testing.assert_array_equal(a[name].values, b[name].values)
    assert set(native_idata.sample_stats.data_vars) == set(python_idata.sample_stats.data_vars)
    np.testing.assert_allclose(a["d"].values, (a["theta"].sum("param") * a["s"]).values)


def test_numpy_physics_samples_through_python_and_says_why():
    """The beam with its numpy physics function: Python Ops, so the Python callback runs and
    the provenance names them."""
    import kohpymc as kp
    from kohpymc.examples import beam

    data = beam.generate_data((2.5,), seed=SEED)
    cal = kp.calibrate(
        beam.physics_model(), data, beam.formulations()["M0"], draws=100, tune=100, chains=2,
        random_seed=SEED,
    )  # fmt: skip
    sampling = json.loads(cal.idata.attrs["sampling"])
    assert sampling["sampler"] == "nutpie"
    assert sampling["nutpie_backend"].startswith("python (native: ValueError: Python-only Op")
    assert "_PhysicsOp" in sampling["nutpie_backend"]
    assert sampling["chain_threads"] == 1
    assert cal.idata.posterior["E"].dims == ("chain", "draw")


def test_python_only_ops_sees_the_physics_op():
    """The numpy physics Op is found; a pure PyTensor graph has none."""
    from kohpymc.examples import beam
    from kohpymc.model import build_model

    data = beam.generate_data((2.5,), seed=SEED)
    model = build_model(beam.physics_model(), data, beam.formulations()["M0"])
    assert "_PhysicsOp" in python_only_ops([model.logp()])
    symbolic = build_model(beam.physics_model(backend="pytensor"), data, beam.formulations()["M0"])
    assert python_only_ops([symbolic.logp()]) == []


def test_a_plan_with_its_own_map_samples_through_python_and_says_why():
    """y = k·c·x with k, c in uniform boxes gets a box-ridge plan, whose map has no
    symbolic form: the Python callback samples it (a native run would have used the
    plan's μ and L as if it were affine), and the informed product is recovered."""
    import kohpymc as kp
    from kohpymc.priors import Uniform

    x = np.linspace(0.05, 1.0, 20)
    rng = np.random.default_rng(SEED)
    data = kp.CalibrationData({"x": x}, 30.0 * x + rng.normal(0.0, 0.5, x.size), noise_sd=0.5)
    physics = kp.PhysicsModel(
        lambda inputs, p: p["k"] * p["c"] * inputs["x"],
        {"k": Uniform(1e-8, 1e-6), "c": Uniform(1e8, 1e10)},
        inputs=["x"],
        backend="pytensor",
    )
    cal = kp.calibrate(physics, data, None, draws=300, tune=300, chains=2, random_seed=SEED)
    sampling = json.loads(cal.idata.attrs["sampling"])
    assert sampling["reparameterization"]["kind"] == "box-ridge-log"
    assert sampling["nutpie_backend"].startswith("python (native: NotImplementedError")
    product = (cal.idata.posterior["k"] * cal.idata.posterior["c"]).values.ravel()
    slope_sd = 0.5 / np.sqrt(np.sum(x**2))  # least-squares sd of the slope k·c
    assert abs(product.mean() - 30.0) < 4 * slope_sd
