"""The measurement design, synthetic data from the hidden truth and the paper's split."""

from __future__ import annotations

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.examples.dielectric.constants import NOISE_SD, T_END, TEMPERATURES, VOLTAGES
from kohpymc.examples.dielectric.current import true_current


def design(n_times: int = 40) -> pd.DataFrame:
    """The 12 (V, T) settings × ``n_times`` equally spaced times ``t_k = 100 k / n_times``.

    Rows are ordered by V, then T, then t.

    Examples
    --------
    >>> d = design()
    >>> len(d), d["t"].iloc[:2].tolist()
    (480, [2.5, 5.0])
    """
    if n_times < 2:
        raise ValueError("design: n_times must be >= 2")
    times = T_END * np.arange(1, n_times + 1) / n_times
    V, T, t = np.meshgrid(VOLTAGES, TEMPERATURES, times, indexing="ij")
    return pd.DataFrame({"V": V.ravel(), "T": T.ravel(), "t": t.ravel()})


def generate_data(seed: int = 0, n_times: int = 40, noise: float = NOISE_SD) -> CalibrationData:
    """Synthetic measurements: :func:`true_current` on :func:`design` plus N(0, noise²).

    The noise sd (nA/cm²) is recorded as known.  One value serves every (V, T) setting:
    :class:`~kohpymc.data.CalibrationData` holds a single σ_obs.

    Examples
    --------
    >>> data = generate_data(seed=1)
    >>> data.n, data.input_names, data.output_name, data.noise_sd
    (480, ('V', 'T', 't'), 'J', 0.3)
    """
    if not noise > 0:
        raise ValueError(f"noise must be > 0, got {noise}")
    rng = np.random.default_rng(seed)
    frame = design(n_times)
    y = true_current(frame) + rng.normal(0.0, noise, size=len(frame))
    return CalibrationData(frame, y, noise_sd=float(noise), output_name="J")


def split_calibration_validation(
    data: CalibrationData,
) -> tuple[CalibrationData, CalibrationData]:
    """Interleaved split of the paper: times t_1, t_3, ... calibrate, t_2, t_4, ... validate.

    The times of each (V, T) setting are ranked; odd ranks (1st, 3rd, ...) go to
    calibration, even ranks to validation.

    Examples
    --------
    >>> cal, val = split_calibration_validation(generate_data())
    >>> cal.n, val.n, cal.inputs["t"][:2].tolist(), val.inputs["t"][:2].tolist()
    (240, 240, [2.5, 7.5], [5.0, 10.0])
    """
    frame = pd.DataFrame({k: data.inputs[k] for k in ("V", "T", "t")})
    rank = frame.groupby(["V", "T"], sort=False)["t"].rank(method="first").to_numpy()
    return data.split(rank % 2 == 1)
