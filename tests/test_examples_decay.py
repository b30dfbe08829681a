"""The decay example: its data files regenerate exactly, its Jacobian is the derivative."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from kohpymc.config import load_study
from kohpymc.examples import decay


@pytest.mark.parametrize(
    ("name", "times", "seed"),
    [("calibration", decay.CALIBRATION_TIMES, 2026), ("validation", decay.VALIDATION_TIMES, 2027)],
)
def test_data_files_are_generate_data(name, times, seed):
    frame = pd.read_csv(decay.STUDY_FILE.parent / "data" / f"decay_{name}.csv")
    data = decay.generate_data(times, seed=seed)
    np.testing.assert_array_equal(frame["t"].to_numpy(), data.inputs["t"])
    np.testing.assert_array_equal(frame["signal"].to_numpy(), data.y)


def test_jacobian_is_the_finite_difference_derivative():
    physics = decay.physics_model()
    inputs = {"t": np.linspace(0.0, 5.0, 11)}
    params = {"A": 1.7, "k": 0.45}
    analytic = physics.jacobian_matrix(inputs, params)
    numeric = physics.finite_difference_jacobian(inputs, params)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-9)


def test_study_file_loads_with_unknown_noise():
    spec = load_study(decay.STUDY_FILE)
    assert spec.calibration.noise_sd is None and spec.calibration.n == 21
    assert spec.physics.parameter_names == ("A", "k")
    assert (spec.check.formulation, spec.check.replicates, spec.check.chains) == ("M0", 200, 2)
