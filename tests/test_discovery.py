"""Term selection on linearised residuals: finds hidden effects, stays quiet on the null."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from kohpymc.candidates import candidate_library, design_matrix
from kohpymc.discovery import select_terms
from kohpymc.examples import beam


def _beam_selection(seed: int, *, hidden: bool):
    rng = np.random.default_rng(seed)
    data = beam.generate_data((2.5, 3.0), seed=seed)
    x, P = data.inputs["x"], data.inputs["P"]
    physics = beam.physics_model()
    y = (
        data.y
        if hidden
        else beam.euler_bernoulli(data.inputs, {"E": 200.0})
        + rng.normal(0.0, data.noise_sd, data.n)
    )
    fit = least_squares(lambda e: physics.evaluate(data.inputs, {"E": e[0]}) - y, [150.0])
    e_hat = float(fit.x[0])
    resid = y - physics.evaluate(data.inputs, {"E": e_hat})
    J = physics.jacobian_matrix(data.inputs, {"E": e_hat})
    inputs = {"x": x, "P": P, "z": rng.uniform(0, 1, data.n)}  # z: irrelevant
    terms = candidate_library(inputs)
    sel = select_terms(
        resid,
        J,
        design_matrix(terms, inputs),
        [t.name for t in terms],
        noise_sd=data.noise_sd,
        parameter_sd=[250 / np.sqrt(12)],
    )
    named = {i for t in terms if t.name in sel.best for i in t.inputs}
    return sel, named


def test_beam_shear_term_depends_on_x_and_p_only():
    sel, named = _beam_selection(2026, hidden=True)
    assert named == {"x", "P"}
    assert sel.probability_none < 1e-6


def test_null_data_gives_at_most_one_false_alarm_in_ten_seeds():
    alarms = sum(bool(_beam_selection(s, hidden=False)[0].best) for s in range(10))
    assert alarms <= 1


def test_bad_input():
    r = np.zeros(3)
    with pytest.raises(ValueError, match="too few data points"):
        select_terms(r, np.ones((3, 2)), np.ones((3, 1)), ["a"], noise_sd=1.0, parameter_sd=[1, 1])
    with pytest.raises(ValueError, match="no candidate"):
        select_terms(r, np.ones((3, 1)), np.ones((3, 0)), [], noise_sd=1.0, parameter_sd=[1])
    with pytest.raises(ValueError, match="every candidate term was rejected"):
        select_terms(
            np.arange(5.0), np.ones((5, 1)), np.ones((5, 1)), ["c"], noise_sd=1.0, parameter_sd=[1]
        )
