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


def test_an_emulator_or_a_bare_function_passed_as_physics_is_named():
    """``kp.calibrate(kp.emulate(...), data)`` failed deep inside with "'Emulator' object has
    no attribute 'inputs'"; the error now says to pass its physics_model()."""
    from kohpymc.emulator import Emulator
    from kohpymc.examples import beam

    data = beam.generate_data(seed=1)
    fake = Emulator.__new__(Emulator)  # an emulator without runs: only its type matters
    with pytest.raises(TypeError, match=r"got an Emulator: pass its physics_model\(\)"):
        compose_model(fake, data)
    with pytest.raises(TypeError, match="got function: wrap it as kp.PhysicsModel"):
        compose_model(beam.euler_bernoulli, data)
