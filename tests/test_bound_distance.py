"""Near-bound parameters sampled by the softplus of their distance to the bound."""

import numpy as np
import pytensor.tensor as pt
import pytest
from scipy.special import expit

from kohpymc.bound_distance import OFFSET, BoundDistanceCoordinates, near_bounds
from kohpymc.native import PYTENSOR
from kohpymc.sampling import sample_posterior
from tests.test_reparameterization import (
    SEED,
    _assert_moments,
    _bounded_model,
    _check_elementwise_map,
    _piled_moments,
)


def _coords(share=(0.01, 0.002)):
    """Element 0 near its upper bound, 1 near its lower, 2 on the log-logit scale."""
    return BoundDistanceCoordinates(
        np.array([False, False, True]),
        np.array([0.8, 16.1, 0.01]),
        np.array([1.4, 25.3, 1.0]),
        near=np.array([True, True, False]),
        sign=np.array([-1.0, 1.0, 0.0]),
        share=np.array([*share, 1.0]),
    )


@pytest.mark.parametrize("w", [[2.0, 2.0, 0.3], [-6.0, 9.0, -1.2], [14.0, -3.0, 2.0]])
def test_map_inverse_and_log_jacobian_against_finite_differences(w):
    """Inverse, dv/dw and d log|dv/dw|/dw against central differences, towards the bound
    (w = −6: 10⁻⁴ of the scale from it), at the scale, and far inside (w = 14)."""
    coords = _coords()
    v, dv, logjac = _check_elementwise_map(coords, np.array(w), h=1e-6, rtol=1e-5, atol=1e-7)
    assert logjac == pytest.approx(np.sum(np.log(np.abs(dv))))
    # over the array namespaces: the same values and log-Jacobian, numpy and PyTensor
    v_np, logjac_np = coords.value_and_log_jacobian(np.array(w))
    v_pt, logjac_pt = coords.value_and_log_jacobian(pt.as_tensor(np.array(w)), PYTENSOR)
    np.testing.assert_allclose(v_np, v, rtol=1e-12)
    np.testing.assert_allclose(v_pt.eval(), v, rtol=1e-12)
    assert float(logjac_np) == pytest.approx(logjac) == pytest.approx(float(logjac_pt.eval()))


def test_the_far_bound_is_never_crossed():
    """Far inside, the distance approaches the prior width without reaching it."""
    coords = _coords(share=(0.5, 0.5))
    v = coords.to_value(np.array([40.0, 40.0, 0.0]))[0]
    x = 0.8 + 0.6 * expit(v[0])
    assert np.isfinite(v).all() and 0.8 < x < 0.8 + 1e-6


def test_an_exponential_pile_up_is_logistic_in_these_coordinates():
    """x ∝ e^{−g(b − x)} on (a, b), g(b − a) = 10⁶: with the share 1/(g(b − a)) the density
    in w (density in x times |dx/dw|, computed here through v) is the logistic
    −softplus(w − 2) − softplus(2 − w) up to a constant, within 10⁻⁴ (the far bound's
    correction is O(g(b − a)·r²), r = softplus(w − 2)/(g(b − a)))."""
    a, b, g = 0.8, 1.4, 1e6 / 0.6
    coords = BoundDistanceCoordinates(
        np.zeros(1, bool), np.array([a]), np.array([b]),
        near=np.ones(1, bool), sign=np.array([-1.0]), share=np.array([1 / (g * (b - a))]),
    )  # fmt: skip
    w = np.linspace(-8.0, 10.0, 37)
    logp = []
    for wi in w:
        v, dv, _, _ = coords.to_value(np.array([wi]))
        gap = (b - a) * expit(-v[0])  # b − x
        logp.append(-g * gap + np.log((b - a) * expit(v[0]) * expit(-v[0]) * abs(dv[0])))
    logistic = -np.logaddexp(0, w - OFFSET) - np.logaddexp(0, OFFSET - w)
    diff = np.array(logp) - logistic
    np.testing.assert_allclose(diff - diff[20], 0.0, atol=1e-4)


def test_near_bounds_are_found_in_laplace_sds_in_own_units():
    """phi's mode (against its upper bound) is near it at a value-space sd of 1, not at
    10⁻⁴ (then 10⁴ sds away); m, far inside its box, never is."""
    from kohpymc.reparameterization import find_mode
    from kohpymc.value_space import value_space

    space = value_space(_bounded_model(phi_true=1.6))
    mode = find_mode(space, seed=SEED).value
    mask, sign = near_bounds(space, mode, np.array([0.01, 1.0]))
    assert mask.tolist() == [False, True] and sign[1] == -1.0
    mask, _ = near_bounds(space, mode, np.array([1e-4, 1e-4]))
    assert not mask.any()


def test_draws_piled_against_a_bound_match_a_dense_reference_without_divergences():
    """φ piled against its upper bound (data from 1.6 beyond 1.4), sampled by its distance
    to it: no divergent transitions (the logit coordinate's double-exponential wall gave
    ~1 %), and the draws' mean, sd and correlation of (m, φ) match dense quadrature within
    4 Monte Carlo errors."""
    model = _bounded_model(phi_true=1.6)
    with pytest.warns(UserWarning, match="upper prior bound 1.4"):
        idata, report = sample_posterior(model, draws=1000, tune=1000, chains=2, random_seed=SEED)
    assert "bound-distance" in report.reparameterization["kind"], report
    assert int(idata.sample_stats.diverging.sum()) == 0
    _assert_moments(idata, ("m", "phi"), *_piled_moments())
