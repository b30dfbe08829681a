"""The noise-funnel map (kohpymc.funnel): exact log-Jacobian, gradient, detection."""

import numpy as np
import pymc as pm
import pytest

from kohpymc.funnel import FunnelPlan, NoiseFunnel, funnel_plan
from kohpymc.reparameterization import plan
from kohpymc.value_space import value_space


def _two_outputs(rows_b: int):
    """``a`` held by 14 rows of known noise; ``b`` by ``rows_b`` rows of unknown noise."""
    rng = np.random.default_rng(3)
    x = np.linspace(1.0, 2.0, rows_b)
    with pm.Model() as model:
        a = pm.Normal("a", 0.0, 10.0)
        b = pm.Uniform("b", -50.0, 50.0)
        s = pm.HalfNormal("s", 40.0)
        pm.Normal("u", a, 0.1, observed=1.0 + rng.normal(0, 0.1, 14))
        pm.Normal("t", a + b * x, s, observed=1.0 + 3.0 * x + rng.normal(0, 2.0, rows_b))
    return value_space(model)


def _funnel(d: int = 4) -> NoiseFunnel:
    rng = np.random.default_rng(0)
    q = rng.normal(size=d)
    q /= np.linalg.norm(q)
    complement = np.linalg.svd(np.eye(d) - np.outer(q, q))[0][:, : d - 1]
    axes = rng.normal(size=(d - 1, d - 1)) + 2 * np.eye(d - 1)
    return NoiseFunnel(1, q, 0.7, complement, axes, np.array([0.0, 0.4, 1.0]), 0.3, 1.4)


def test_map_inverts_and_its_log_jacobian_is_the_log_determinant():
    funnel = _funnel()
    rng = np.random.default_rng(1)
    for _ in range(5):
        y = rng.normal(size=4) * 2.0
        z, logjac = funnel.forward(y)
        np.testing.assert_allclose(funnel.inverse(z), y, atol=1e-10)
        h = 1e-6
        jac = np.column_stack(
            [(funnel.forward(y + h * e)[0] - funnel.forward(y - h * e)[0]) / (2 * h)
             for e in np.eye(4)]
        )  # fmt: skip
        constant = np.log(abs(np.linalg.det(funnel.axes)))  # left out of the density
        assert logjac + constant == pytest.approx(np.log(abs(np.linalg.det(jac))), abs=1e-6)


def test_pull_back_is_the_gradient_of_the_density_in_y():
    funnel = _funnel()

    def density(y):  # f(z) = -|z - c|^2 / 2 plus the map's log-Jacobian
        z, logjac = funnel.forward(y)
        return -0.5 * np.sum((z - 0.3) ** 2) + logjac

    y = np.array([0.8, -1.0, 0.5, 1.5])
    z, _ = funnel.forward(y)
    grad = funnel.pull_back(y, -(z - 0.3))
    h = 1e-6
    numeric = [(density(y + h * e) - density(y - h * e)) / (2 * h) for e in np.eye(4)]
    np.testing.assert_allclose(grad, numeric, atol=1e-6)


def test_plan_density_is_the_posterior_carried_by_the_map():
    space = _two_outputs(3)
    wrapped = funnel_plan(space, plan(space, seed=1))
    assert isinstance(wrapped, FunnelPlan)
    y = np.array([0.4, -0.7, 1.1])
    logp, grad = wrapped.logp_dlogp(space, y)
    inner_z, logjac = wrapped.funnel.forward(y)
    assert logp == pytest.approx(wrapped.inner.logp_dlogp(space, inner_z)[0] + logjac)
    h = 1e-6
    numeric = [
        (wrapped.logp_dlogp(space, y + h * e)[0] - wrapped.logp_dlogp(space, y - h * e)[0])
        / (2 * h)
        for e in np.eye(3)
    ]
    np.testing.assert_allclose(grad, numeric, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(wrapped.from_value(wrapped.to_value(y)), y, atol=1e-9)


def test_funnel_found_for_three_rows_and_not_for_sixty():
    few = _two_outputs(3)
    wrapped = funnel_plan(few, plan(few, seed=1))
    assert wrapped is not None and wrapped.funnel.index == few.names.index("s_log__")
    assert "a funnel between s and" in wrapped.reason
    many = _two_outputs(60)
    assert funnel_plan(many, plan(many, seed=1)) is None
