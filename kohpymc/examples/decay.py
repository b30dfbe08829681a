"""A first-order decay with unknown measurement noise: ``y = A exp(-k t) + ε``.

A signal (a concentration in a first-order reaction, the activity of a radioactive
source, the voltage over a discharging capacitor) starts at amplitude ``A`` and decays
at rate ``k`` (1/s); it is measured at times ``t`` with Gaussian noise whose standard
deviation is *not* known and is calibrated with the physics parameters.  Both
parameters are positive, with log-normal priors: ``A ~ LogNormal(0, 1)`` (median 1,
95 % between 0.14 and 7.1) and ``k ~ LogNormal(ln 0.5, 0.75)`` (median 0.5 1/s, 95 %
between 0.11 and 2.2 1/s).

The synthetic data of ``decay_study.toml`` (``data/decay_calibration.csv``,
``data/decay_validation.csv``) are :func:`generate_data` with the true values
:data:`TRUE_A`, :data:`TRUE_K` and noise sd :data:`NOISE_SD`.  The study serves as the
small, fast model of ``kohpymc check`` (simulation-based calibration, :mod:`kohpymc.sbc`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.physics import PhysicsModel
from kohpymc.priors import LogNormal

__all__ = [
    "TRUE_A",
    "TRUE_K",
    "NOISE_SD",
    "CALIBRATION_TIMES",
    "VALIDATION_TIMES",
    "STUDY_FILE",
    "exponential_decay",
    "exponential_decay_jacobian",
    "physics_model",
    "generate_data",
]

TRUE_A = 2.0  # amplitude at t = 0 (units of the signal)
TRUE_K = 0.7  # decay rate, 1/s
NOISE_SD = 0.05  # measurement-noise sd (units of the signal)
#: 21 times from 0 to 5 s, every 0.25 s
CALIBRATION_TIMES = tuple(np.round(np.linspace(0.0, 5.0, 21), 2).tolist())
#: 6 later times, 5.5 to 8 s: the validation extrapolates
VALIDATION_TIMES = (5.5, 6.0, 6.5, 7.0, 7.5, 8.0)
#: the study file of this example (``kohpymc study`` / ``kohpymc check``)
STUDY_FILE = Path(__file__).with_name("decay_study.toml")


def exponential_decay(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
    """``A exp(-k t)`` at the times ``inputs["t"]``.

    Examples
    --------
    >>> exponential_decay({"t": np.array([0.0, 1.0])}, {"A": 2.0, "k": np.log(2.0)})
    array([2., 1.])
    """
    return params["A"] * np.exp(-params["k"] * np.asarray(inputs["t"], dtype=float))


def exponential_decay_jacobian(
    inputs: Mapping[str, Any], params: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """``∂y/∂A = exp(-k t)`` and ``∂y/∂k = -A t exp(-k t)``.

    Examples
    --------
    >>> jac = exponential_decay_jacobian({"t": np.array([1.0])}, {"A": 2.0, "k": 0.0})
    >>> float(jac["A"][0]), float(jac["k"][0])
    (1.0, -2.0)
    """
    t = np.asarray(inputs["t"], dtype=float)
    e = np.exp(-params["k"] * t)
    return {"A": e, "k": -params["A"] * t * e}


def physics_model() -> PhysicsModel:
    """The decay model with its log-normal priors on ``A`` and ``k``.

    Examples
    --------
    >>> physics_model().parameter_names
    ('A', 'k')
    """
    return PhysicsModel(
        exponential_decay,
        {"A": LogNormal(0.0, 1.0), "k": LogNormal(float(np.log(0.5)), 0.75)},
        inputs=["t"],
        jacobian=exponential_decay_jacobian,
        name="exponential_decay",
    )


def generate_data(
    times: Sequence[float] = CALIBRATION_TIMES,
    *,
    seed: int = 0,
    A: float = TRUE_A,
    k: float = TRUE_K,
    noise_sd: float = NOISE_SD,
) -> CalibrationData:
    """Synthetic measurements ``A exp(-k t) + N(0, noise_sd²)``; the noise sd is not recorded.

    Examples
    --------
    >>> data = generate_data(seed=1)
    >>> data.n, data.output_name, data.noise_sd is None
    (21, 'signal', True)
    """
    t = np.asarray(times, dtype=float)
    rng = np.random.default_rng(seed)
    y = exponential_decay({"t": t}, {"A": A, "k": k}) + rng.normal(0.0, noise_sd, size=t.size)
    return CalibrationData(pd.DataFrame({"t": t}), np.round(y, 6), output_name="signal")
