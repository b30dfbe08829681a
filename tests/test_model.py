"""Composing the PyMC model: the physics runs once per data set before any sampling."""

from __future__ import annotations

import numpy as np
import pytest

from kohpymc import (
    CalibrationData,
    ConstantBias,
    IIDGaussian,
    NoDiscrepancy,
    PhysicsModel,
    PhysicsModelError,
    Uniform,
)
from kohpymc.model import compose_model


def _line(inputs, params):
    return params["a"] * inputs["x"]


def test_the_physics_check_runs_once_per_data_set_and_still_catches_a_failure():
    """An expensive simulator is not re-run to compose every formulation of a study."""
    physics = PhysicsModel(_line, {"a": Uniform(0.0, 2.0)}, ["x"])
    data = CalibrationData({"x": np.linspace(0.0, 1.0, 5)}, np.zeros(5), noise_sd=0.1)
    for formulation in (NoDiscrepancy(), ConstantBias(), IIDGaussian()):
        compose_model(physics, data, formulation)
    assert physics.n_calls == 1
    other = CalibrationData({"x": np.linspace(0.0, 2.0, 4)}, np.zeros(4), noise_sd=0.1)
    compose_model(physics, other)
    assert physics.n_calls == 2

    def broken(inputs, params):
        return np.full(inputs["x"].size, np.nan)

    bad = PhysicsModel(broken, {"a": Uniform(0.0, 2.0)}, ["x"])
    for _ in range(2):  # a failure is not remembered as checked
        with pytest.raises(PhysicsModelError):
            compose_model(bad, data)
