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
