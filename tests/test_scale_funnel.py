"""The scale-funnel map (kohpymc.scale_funnel): exact map, detection, draws against quadrature."""

import numpy as np
import pymc as pm
import pytest
from scipy.interpolate import CubicSpline

from kohpymc.funnel import FunnelPlan
from kohpymc.reparameterization import plan
from kohpymc.scale_funnel import ScaleFunnel, scale_funnel_plan
from kohpymc.value_space import value_space
from tests.test_reparameterization import (
    _finite_difference_gradient,
    _finite_difference_jacobian,
)

#: three rows of a line whose discrepancy sd grows with x, over a noise sd of 0.05
_X = np.linspace(1.0, 3.0, 3)
_S0 = 0.05


def _rows() -> np.ndarray:
    rng = np.random.default_rng(4)
    return 1.0 + 2.0 * _X + rng.normal(0.0, _S0, _X.size) * (1.0 + _X)


def _line_model() -> pm.Model:
    """``y_i ~ N(a + b x_i, 0.05² + τ² x_i²)``: the line's conditional sds grow with τ."""
    with pm.Model() as model:
        a = pm.Uniform("a", -50.0, 50.0)
        b = pm.Uniform("b", -50.0, 50.0)
        tau = pm.HalfNormal("tau", 1.0)
        pm.Normal("y", a + b * _X, pm.math.sqrt(_S0**2 + tau**2 * _X**2), observed=_rows())
    return model


def _funnel(d: int = 4) -> ScaleFunnel:
    rng = np.random.default_rng(0)
    q = rng.normal(size=d)
    q /= np.linalg.norm(q)
    complement = np.linalg.svd(np.eye(d) - np.outer(q, q))[0][:, : d - 1]
    nodes = np.linspace(-3.0, 3.0, 7)
    modes = np.column_stack([np.sin(nodes), 0.3 * nodes**2, -0.2 * nodes])
    n = d - 1
    entries = np.column_stack(
        [0.4 * nodes, -0.2 * nodes, 0.1 * np.cos(nodes), 0.3 + 0.1 * nodes,
         0.2 * np.sin(nodes), -0.1 * nodes]
    )  # fmt: skip
    assert entries.shape[1] == n + n * (n - 1) // 2
    return ScaleFunnel(1, q, complement, nodes, CubicSpline(nodes, modes, axis=0),
                       CubicSpline(nodes, entries, axis=0), None, 0.2, 1.3)  # fmt: skip


@pytest.mark.parametrize("y0", [0.4, 3.5])  # inside the nodes, and beyond the last one
def test_map_inverts_and_its_log_jacobian_is_the_log_determinant(y0):
    funnel = _funnel()
    y = np.array([y0, -0.7, 1.2, 0.5])
    z, logjac = funnel.forward(y)
    np.testing.assert_allclose(funnel.inverse(z), y, atol=1e-10)
    jac = _finite_difference_jacobian(lambda x: funnel.forward(x)[0], y)
    assert logjac == pytest.approx(np.log(abs(np.linalg.det(jac))), abs=1e-6)


@pytest.mark.parametrize("y0", [0.4, -3.1])
def test_pull_back_is_the_gradient_of_the_density_in_y(y0):
    funnel = _funnel()

    def density(y):
        z, logjac = funnel.forward(y)
        return -0.5 * np.sum((z - 0.3) ** 2) + logjac

    y = np.array([y0, -1.0, 0.5, 1.5])
    z, _ = funnel.forward(y)
    grad = funnel.pull_back(y, -(z - 0.3))
    numeric = _finite_difference_gradient(density, y)
    np.testing.assert_allclose(grad, numeric, atol=1e-6)


def test_funnel_of_a_discrepancy_sd_is_found_and_carries_the_posterior():
    space = value_space(_line_model())
    inner = plan(space, seed=1)
    wrapped = scale_funnel_plan(space, inner, ["tau"])
    assert scale_funnel_plan(space, inner) is None  # no scale named
    assert isinstance(wrapped, FunnelPlan) and isinstance(wrapped.funnel, ScaleFunnel)
    assert wrapped.funnel.index == space.names.index("tau_log__")
    assert "a funnel between tau and the rest" in wrapped.reason
    assert wrapped.gaussian_score < inner.gaussian_score
    y = np.array([0.4, -0.7, 1.1])
    logp, grad = wrapped.logp_dlogp(space, y)
    inner_z, logjac = wrapped.funnel.forward(y)
    assert logp == pytest.approx(inner.logp_dlogp(space, inner_z)[0] + logjac)
    numeric = _finite_difference_gradient(lambda x: wrapped.logp_dlogp(space, x)[0], y)
    np.testing.assert_allclose(grad, numeric, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(wrapped.from_value(wrapped.to_value(y)), y, atol=1e-9)


def _quadrature_moments() -> dict[str, float]:
    """E[a], E[b], E[ln τ] by quadrature: (a, b) in closed form given τ, ln τ on a grid.

    Given τ the likelihood is Gaussian in (a, b) with covariance ``(Xᵀ W X)⁻¹``,
    ``W = diag(1/(0.05² + τ² x²))``; the box (±50) is hundreds of its sds wide, so it is
    taken as flat.  The weight of ln τ is the marginal likelihood times the HalfNormal(1)
    prior and the log-Jacobian.
    """
    y = _rows()
    design = np.column_stack([np.ones_like(_X), _X])
    ln_tau = np.linspace(-14.0, 3.0, 20001)
    weights, coefficients = [], []
    for lt in ln_tau:
        w = 1.0 / (_S0**2 + np.exp(2 * lt) * _X**2)
        precision = design.T @ (w[:, None] * design)
        beta = np.linalg.solve(precision, design.T @ (w * y))
        resid = y - design @ beta
        log_ml = 0.5 * np.sum(np.log(w)) - 0.5 * np.sum(w * resid**2)
        log_ml -= 0.5 * np.linalg.slogdet(precision)[1]
        weights.append(log_ml - 0.5 * np.exp(2 * lt) + lt)
        coefficients.append(beta)
    log_w = np.array(weights)
    p = np.exp(log_w - log_w.max())
    p /= p.sum()
    beta = np.array(coefficients)
    return {"a": float(p @ beta[:, 0]), "b": float(p @ beta[:, 1]),
            "ln_tau": float(p @ ln_tau)}  # fmt: skip


def test_line_with_a_discrepancy_sd_samples_the_quadrature_posterior():
    """Three rows, a line, a discrepancy sd growing with x over a known noise sd.

    Before the map (the Laplace plan alone), seeds 1 and 2, 2 × 1000 draws: 34 and 18
    divergent transitions, bulk ESS 128 and 126 (r̂ 1.024, 1.037); with it 0 and 0,
    ESS 1706 and 1212.
    """
    import arviz as az

    from kohpymc.sampling import sample_posterior

    idata, report = sample_posterior(
        _line_model(), chains=2, random_seed=1, scale_parameters=["tau"]
    )
    assert report.reparameterization["kind"].startswith("scale-funnel")
    post = idata.posterior
    draws = {"a": post["a"], "b": post["b"], "ln_tau": np.log(post["tau"])}
    reference = _quadrature_moments()
    for name, values in draws.items():
        frame = values.rename("x").to_dataset()
        mcse = float(az.mcse(frame)["x"])
        assert abs(float(values.mean()) - reference[name]) < 4 * mcse, name
        assert float(az.ess(frame)["x"]) > 400, name
    assert int(idata.sample_stats["diverging"].sum()) == 0
