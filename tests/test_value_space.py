"""kohpymc.value_space: the expand map in its own compile mode gives the same values."""

from __future__ import annotations

import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt

from kohpymc import PhysicsModel, Uniform
from kohpymc.value_space import _expand_mode, value_space


def _model() -> pm.Model:
    with pm.Model() as model:
        a = pm.Uniform("a", 50.0, 300.0)
        s = pm.HalfNormal("s", 1.0)
        pm.Deterministic("ratio", a / (1.0 + s))
        pm.Normal("y", a / 100.0, s, observed=[1.0, 1.5, 2.0])
    return model


def test_expand_of_a_numba_space_matches_the_c_backend():
    model = _model()
    numba, c = value_space(model, mode="NUMBA"), value_space(model, mode="FAST_RUN")
    x = np.array([0.3, -0.2])
    for name, value in numba.expand(x).items():
        np.testing.assert_allclose(value, c.expand(x)[name], rtol=1e-12)
    np.testing.assert_allclose(numba.logp_dlogp(x)[0], c.logp_dlogp(x)[0], rtol=1e-12)


def test_expand_mode_is_c_for_numba_only_with_a_compiler_and_a_python_op():
    """A Python Op (a numpy physics function) in the map: C; a pure PyTensor map: NUMBA."""
    decay = PhysicsModel(
        lambda x, p: p["a"] * np.exp(-x["t"]), {"a": Uniform(1.0, 2.0)}, inputs=["t"]
    )
    theta = pt.vector("theta")
    python_op = decay.tensor(theta, pt.as_tensor(np.array([[0.0], [1.0]])))
    with_compiler = "FAST_RUN" if pytensor.config.cxx else "NUMBA"
    assert _expand_mode("NUMBA", [python_op]) == with_compiler
    assert _expand_mode("NUMBA") == with_compiler
    assert _expand_mode("NUMBA", [pt.exp(theta)]) == "NUMBA"
    assert _expand_mode(None) is None


def test_numba_space_reads_shared_data_at_each_call():
    """The NUMBA log density is called through kohpymc's own numba function (the graph
    inlined): it reads the model's shared data at every call, as the C backend does."""
    data = pytensor.shared(np.array([1.0, 1.5, 2.0]), name="y_obs")
    with pm.Model() as model:
        a = pm.Normal("a", 0.0, 10.0)
        s = pm.HalfNormal("s", 1.0)
        pm.Normal("y", a, s, observed=data)
    numba, c = value_space(model, mode="NUMBA"), value_space(model, mode="FAST_RUN")
    x = np.array([0.7, -0.4])
    for values in ([1.0, 1.5, 2.0], [-3.0, 0.2, 5.0]):
        data.set_value(np.array(values))
        expected_logp, expected_grad = c.logp_dlogp(x)
        logp, grad = numba.logp_dlogp(x)
        np.testing.assert_allclose(logp, expected_logp, rtol=1e-12)
        np.testing.assert_allclose(grad, expected_grad, rtol=1e-12)


def test_lean_uniform_terms_give_pymcs_log_density_and_gradient():
    """value_logp against PyMC's own model.logp() (both with Jacobians): a scalar and a
    vector Uniform (array bounds), a Uniform with a log transform (left as PyMC builds it),
    a HalfNormal and a Potential, at random points and far into the logit tails (|x| up
    to 800, where θ rounds onto its bound), to 1e-12; the lean graph is smaller."""
    from pytensor.graph.traversal import applys_between

    from kohpymc.value_space import value_logp

    with pm.Model() as model:
        a = pm.Uniform("a", 50.0, 300.0)
        b = pm.Uniform("b", np.array([0.0, -2.0, 1e-3]), np.array([1.0, 5.0, 2e-3]), shape=3)
        c = pm.Uniform("c", 0.5, 4.0, default_transform=pm.distributions.transforms.log)
        s = pm.HalfNormal("s", 1.0)
        pm.Potential("wall", -((b[0] - 0.5) ** 2))
        pm.Normal("y", a / 100.0 + b.sum() * c, s, observed=[1.0, 1.5, 2.0])
    inputs = model.value_vars
    lean, pymc_logp = value_logp(model), model.logp()
    outputs = [lean, *pytensor.grad(lean, inputs), pymc_logp, *pytensor.grad(pymc_logp, inputs)]
    f = pytensor.function(inputs, outputs)
    rng = np.random.default_rng(7)
    points = [[rng.normal(0, 2), rng.normal(0, 2, 3), rng.normal(0.5, 0.3), rng.normal()]]
    points += [[x, np.array([-x, x, 0.1]), 0.2, 0.0] for x in (-800.0, -40.0, 40.0, 800.0)]
    for point in points:
        values = f(*[np.asarray(v, dtype=float) for v in point])
        for got, expected in zip(values[:5], values[5:], strict=True):
            np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    nodes = [len(list(applys_between(inputs, [g]))) for g in (lean, pymc_logp)]
    assert nodes[0] < nodes[1] - 80


def test_transformed_value_in_numpy_equals_pymcs_transform():
    """The numpy log and interval transforms against PyMC's own forward graphs."""
    from kohpymc.value_space import transformed_value

    with pm.Model() as model:
        a = pm.Uniform("a", np.array([0.0, -2.0]), np.array([1.0, 5.0]), shape=2)
        s = pm.HalfNormal("s", 1.0)
        h = pm.Uniform("h", 0.0, np.inf)  # infinite bound: PyMC's graph evaluates it
    for rv, values in ((a, [[0.2, 4.0], [0.9, -1.5]]), (s, [0.3, 2.0]), (h, [0.5, 7.0])):
        transform = model.rvs_to_transforms[rv]
        expected = transform.forward(np.asarray(values), *rv.owner.inputs).eval()
        np.testing.assert_allclose(transformed_value(model, rv, values), expected, rtol=1e-14)


def test_expand_rows_of_a_numba_space_match_the_c_backends_expand_row_by_row():
    """The batched map (numpy, no compile) of a model whose deterministic needs a Cholesky
    factor and solves, as the marginalised formulations' coefficients do."""
    with pm.Model() as model:
        a = pm.Uniform("a", 50.0, 300.0)
        s = pm.HalfNormal("s", 1.0)
        w = pm.Normal("w", 0.0, 1.0, shape=2)
        cov = pt.stack([[1.0 + s, 0.3 * s], [0.3 * s, 2.0]])
        pm.Deterministic("coef", pt.linalg.solve_triangular(pt.linalg.cholesky(cov), w))
        pm.Deterministic("ratio", a / (1.0 + s) + s + w[0])
        pm.Normal("y", a / 100.0 + w[1], s, observed=[1.0, 1.5, 2.0])
    numba, c = value_space(model, mode="NUMBA"), value_space(model, mode="FAST_RUN")
    assert numba._expand_rows is not None
    rows = np.random.default_rng(5).normal(size=(50, numba.ndim))
    got = numba.expand_rows(rows)
    assert set(got) == set(c.expanded_names)
    for r, row in enumerate(rows):
        for name, value in c.expand(row).items():
            np.testing.assert_allclose(got[name][r], value, rtol=1e-12)
            np.testing.assert_allclose(numba.expand(row)[name], value, rtol=1e-12)


def test_numba_density_is_one_c_function_with_integer_data_and_errors_reported():
    """The NUMBA density runs as one numba C function (graph compiled once), reading
    float and integer shared data at each call, against the C backend to 1e-12; where the
    graph raises (an Assert on a parameter) the strict
    call raises the graph's own error and the tolerant one gives -inf, with nothing
    printed by numba's C wrapper."""
    import contextlib
    import io
    import sys

    from pytensor.raise_op import Assert

    data = pytensor.shared(np.array([1.0, 1.5, 2.0]), name="y_obs")
    power = pytensor.shared(np.int64(2), name="power")
    with pm.Model() as model:
        a = pm.Normal("a", 0.0, 10.0)
        s = pm.Normal("s", 0.0, 1.0)
        checked = Assert("s above -1")(s, pt.gt(s, -1.0))
        mean = a + 0.0 * checked**power
        pm.Potential("gauss", -0.5 * pt.sum((data - mean) ** 2) / (1.0 + checked) ** 2)
    numba, c = value_space(model, mode="NUMBA"), value_space(model, mode="FAST_RUN")
    assert numba._logp_dlogp.c_function is not None
    x = np.array([0.7, -0.4])
    for values, exponent in (([1.0, 1.5, 2.0], 2), ([-3.0, 0.2, 5.0], 4)):
        data.set_value(np.array(values))
        power.set_value(np.int64(exponent))
        expected_logp, expected_grad = c.logp_dlogp(x)
        logp, grad = numba.logp_dlogp(x)
        np.testing.assert_allclose(logp, expected_logp, rtol=1e-12)
        np.testing.assert_allclose(grad, expected_grad, rtol=1e-12)
    bad = np.array([0.7, -1.5])
    stderr, seen = io.StringIO(), []
    previous_hook = sys.unraisablehook
    sys.unraisablehook = seen.append
    try:
        with contextlib.redirect_stderr(stderr):
            logp, grad = numba.logp_dlogp_or_nan(bad)
    finally:
        sys.unraisablehook = previous_hook
    assert logp == -np.inf and np.all(np.isnan(grad))
    assert seen == [] and stderr.getvalue() == ""
    with np.testing.assert_raises(Exception):
        c.logp_dlogp(bad)
    with np.testing.assert_raises(Exception):
        numba.logp_dlogp(bad)


def test_value_space_of_a_model_singular_at_its_initial_point():
    """``ka/(ka - ke)`` with equal priors: 0/0 at the initial point, where the expand map ran.

    A formulation with a deterministic of the physics (M1's ``y_model``) raised there; the
    shapes are now taken next to it, and the map still gives the physics there exactly.
    """
    import kohpymc as kp
    from kohpymc.model import compose_model

    def oral(inputs, params):
        ka, ke, t = np.float64(params["ka"]), np.float64(params["ke"]), inputs["t"]
        with np.errstate(all="ignore"):
            return ka / (ka - ke) * (np.exp(-ke * t) - np.exp(-ka * t))

    prior = kp.LogUniform(0.01, 10)
    physics = kp.PhysicsModel(oral, {"ka": prior, "ke": prior}, inputs=["t"])
    t = np.linspace(0.25, 24, 12)
    data = kp.CalibrationData({"t": t}, oral({"t": t}, {"ka": 1.0, "ke": 0.1}), noise_sd=0.01)
    space = value_space(compose_model(physics, data, kp.ConstantBias()).model)
    x = space.initial + np.linspace(0.01, 0.02, space.ndim)
    values = space.expand(x)
    assert np.isfinite(space.logp_dlogp(x)[0])
    assert values["ka"] != values["ke"]
