"""benchmarks/scale.py: the structured (replicate + Kronecker) GP likelihood is exact."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import scale  # noqa: E402


@pytest.fixture(scope="module")
def small() -> scale.GridData:
    """2 × 2 settings × 10 times × 3 replicates (120 raw points)."""
    rng = np.random.default_rng(3)
    grids = (np.array([10.0, 30.0]), np.array([300.0, 390.0]), scale.times(10))
    V, T, t = grids[0][:, None, None], grids[1][None, :, None], grids[2][None, None, :]
    f = scale.physics(V, T, t, **scale.TRUE_PARAMS) + scale.discrepancy(V, T, t)
    y = f[..., None] + rng.normal(0.0, 0.2, size=f.shape + (3,))
    return scale.GridData(grids, y, 0.2)


def _random_params(rng: np.random.Generator) -> dict:
    return {
        "A": rng.uniform(1.0, 3.0),
        "tau300": rng.uniform(10.0, 60.0),
        "E_a": rng.uniform(0.1, 0.4),
        "eta": rng.uniform(0.2, 2.0),
        "ls": np.array([rng.uniform(5, 40), rng.uniform(20, 150), rng.uniform(5, 60)]),
    }


def _graphs(data: scale.GridData):
    """Symbolic structured and dense log-likelihoods of the same parameters."""
    A, tau, Ea, eta = (pt.dscalar(k) for k in ("A", "tau300", "E_a", "eta"))
    ls = pt.dvector("ls")
    V, T, t = data.mesh()
    resid = pt.as_tensor_variable(data.ybar) - scale.physics(V, T, t, A, tau, Ea, xp=pt)
    s2 = data.sigma**2 / data.replicates
    structured = scale.kron_gp_loglik(resid, data.grids, eta, ls, s2)
    structured = structured + scale.replicate_constant(data)

    X = data.raw_inputs()
    G = scale.physics(X[:, 0], X[:, 1], X[:, 2], A, tau, Ea, xp=pt)
    K = eta**2 * pt.prod(
        pt.stack(
            [pt.exp(-0.5 * (X[:, k, None] - X[None, :, k]) ** 2 / ls[k] ** 2) for k in range(3)]
        ),
        axis=0,
    )
    cov = K + data.sigma**2 * pt.eye(len(X))
    dense = pm.logp(pm.MvNormal.dist(mu=G, cov=cov), data.y.reshape(-1))
    inputs = [A, tau, Ea, eta, ls]
    fns = [pytensor.function(inputs, [f, *pt.grad(f, inputs)]) for f in (structured, dense)]
    return fns


def test_structured_loglik_matches_dense(small):
    f_struct, f_dense = _graphs(small)
    rng = np.random.default_rng(11)
    for _ in range(4):
        p = _random_params(rng)
        args = [p[k] for k in ("A", "tau300", "E_a", "eta", "ls")]
        v_s, *g_s = f_struct(*args)
        v_d, *g_d = f_dense(*args)
        np.testing.assert_allclose(v_s, v_d, rtol=1e-8)
        # numpy/scipy dense Cholesky of the raw data (used in the benchmark's check)
        np.testing.assert_allclose(v_s, scale.dense_loglik(small, p), rtol=1e-8)
        for a, b in zip(g_s, g_d, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-8 * abs(v_d))


def test_model_loglik_is_raw_likelihood(small):
    model = scale.build_model(small)
    outs = model.unobserved_value_vars
    fn = model.compile_fn(outs, inputs=model.value_vars, on_unused_input="ignore")
    res = dict(zip([v.name for v in outs], fn(model.initial_point()), strict=True))
    np.testing.assert_allclose(res["loglik"], scale.dense_loglik(small, res), rtol=1e-8)
