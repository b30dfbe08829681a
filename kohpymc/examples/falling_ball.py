"""Real data: drop times of a falling ball against the drag-free fall law.

Data
----
63 measured fall times ``time_s`` (s) of a ball dropped from 21 heights ``height_m``
(m, 0.178–4.272 m), three replicates per height, in ``examples/data/falling_ball.csv``.
They come from Example 3 of the surmise project (bandframework/surmise,
``examples/Example3/ball.csv``; MIT licence, Copyright (c) 2023 The Surmise Development
Team) and are also used in R. B. Gramacy, *Surrogates* (2020), chapter 8.  The file is
an unchanged copy; see ``examples/data/README.md``.

Physics model
-------------
Fall from rest without air resistance, ``h = g t² / 2``, so

    t(h; g) = sqrt(2 h / g),      ∂t/∂g = -t / (2 g),

with the gravitational acceleration ``g`` (m/s²) calibrated.  Air drag is not in the
model, so the real fall times are longer than ``t(h; 9.81)`` by an amount that grows
with the height: for a small quadratic drag with terminal speed ``v_T`` the excess is
``≈ g² t³ / (12 v_T²) ∝ h^{3/2}`` (``∝ h`` for linear drag).  A model that ignores it
can only explain long times with a small ``g``.

Calibration and validation
--------------------------
The heights have a gap between 1.958 m and 2.670 m.  :func:`split_at_gap` calibrates on
the 11 heights below it (33 rows) and validates on the 10 above (30 rows): an honest
extrapolation test, since the drag signal is strongest in the validation range.

Noise
-----
σ_obs is not known; it is the pooled within-height sd of the replicates (paper Eq. 28),
``load_data`` passes ``replicates="inputs"``.  Pooled over all 63 rows it is 0.072 s,
over the calibration rows alone 0.054 s and over the validation rows 0.088 s: the
timing scatter itself grows with height.  :func:`split_at_gap` re-pools each part on its
own rows so the calibration noise uses no validation measurement.

Reference
---------
``G_REFERENCE = 9.81`` m/s² (local values on Earth lie within 9.78–9.83 m/s²) is a
yardstick for the calibrated ``g``, not part of any prior.
"""

from __future__ import annotations

from collections.abc import Mapping
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from kohpymc.data import CalibrationData
from kohpymc.discrepancy import Discrepancy
from kohpymc.physics import PhysicsModel
from kohpymc.priors import Uniform

__all__ = [
    "DATA_FILE",
    "G_REFERENCE",
    "G_PRIOR_RANGE",
    "GAP",
    "SPLIT_HEIGHT",
    "TOLERANCE",
    "drag_free_time",
    "drag_free_time_jacobian",
    "physics_model",
    "load_data",
    "split_at_gap",
    "formulations",
]

#: the shipped copy of the data (surmise Example 3, MIT licence)
DATA_FILE = Path(__file__).parent / "data" / "falling_ball.csv"
#: m/s², textbook gravitational acceleration, a yardstick for the posterior of g
G_REFERENCE = 9.81
#: m/s², bounds of the uniform prior of g (see :func:`physics_model`)
G_PRIOR_RANGE = (5.0, 15.0)
#: m, the last height below and the first height above the gap in the design
GAP = (1.958, 2.670)
#: m, heights below this calibrate, heights above validate
SPLIT_HEIGHT = 2.3
#: s, ε of the reliability metric: about 10 % of the mean validation fall time (0.94 s)
#: and 1.4 times the pooled replicate sd (0.072 s), while the drag excess at the top
#: heights (0.15–0.2 s over sqrt(2 h / 9.81)) is well beyond it
TOLERANCE = 0.1


def drag_free_time(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
    """Fall time from rest without air resistance, ``t = sqrt(2 h / g)`` (s).

    Parameters
    ----------
    inputs : mapping
        ``height_m``: drop heights (m).
    params : mapping
        ``g``: gravitational acceleration (m/s²).

    Returns
    -------
    numpy.ndarray
        Fall times (s), one per height.

    Examples
    --------
    >>> float(drag_free_time({"height_m": 4.905}, {"g": 9.81}))
    1.0
    """
    height = np.asarray(inputs["height_m"], dtype=float)
    return np.sqrt(2.0 * height / params["g"])


def drag_free_time_jacobian(
    inputs: Mapping[str, Any], params: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """``∂t/∂g = -t / (2 g) = -sqrt(h / (2 g³))``.

    Examples
    --------
    >>> round(float(drag_free_time_jacobian({"height_m": 4.905}, {"g": 9.81})["g"]), 6)
    -0.050968
    """
    return {"g": -drag_free_time(inputs, params) / (2.0 * params["g"])}


def physics_model(*, jacobian: bool = True) -> PhysicsModel:
    """The drag-free fall law with ``g ~ Uniform(5, 15)`` m/s².

    The prior is what one would write down before seeing these data: it is centred near
    the textbook value but a factor of two wide, so that it excludes only physically
    absurd values and leaves a biased calibration free to show its bias.  Its centre,
    10 m/s², is the expansion point of the identifiability check.

    Parameters
    ----------
    jacobian : bool
        Use the analytic ``∂t/∂g``; ``False`` exercises finite differences.

    Examples
    --------
    >>> physics_model().parameter_names
    ('g',)
    """
    return PhysicsModel(
        drag_free_time,
        {"g": Uniform(*G_PRIOR_RANGE)},
        inputs=["height_m"],
        jacobian=drag_free_time_jacobian if jacobian else None,
        name="drag_free_fall",
    )


def load_data(path: str | PathLike[str] | None = None) -> CalibrationData:
    """All 63 drop times, with σ_obs pooled from the three replicates per height (Eq. 28).

    Parameters
    ----------
    path : path, optional
        A CSV with columns ``height_m`` and ``time_s``; default :data:`DATA_FILE`.

    Examples
    --------
    >>> data = load_data()
    >>> data.n, data.input_names, data.output_name, round(data.noise_sd, 4)
    (63, ('height_m',), 'time_s', 0.0718)
    """
    return CalibrationData.from_csv(
        DATA_FILE if path is None else path,
        inputs=["height_m"],
        output="time_s",
        replicates="inputs",
    )


def split_at_gap(
    data: CalibrationData, at: float = SPLIT_HEIGHT
) -> tuple[CalibrationData, CalibrationData]:
    """Split into ``(heights below at, heights above at)``: calibration and validation.

    When the noise sd of ``data`` was pooled from replicates, each part gets the pooled
    sd of its own replicates (as if read from its own file), so the calibration noise
    does not use validation measurements.

    Parameters
    ----------
    data : CalibrationData
        The drop times (:func:`load_data`).
    at : float
        Split height (m), default in the gap between 1.958 m and 2.670 m.

    Examples
    --------
    >>> cal, val = split_at_gap(load_data())
    >>> cal.n, val.n, float(cal.inputs["height_m"].max()), float(val.inputs["height_m"].min())
    (33, 30, 1.958, 2.67)
    """
    below = data.inputs["height_m"] < at
    parts = []
    for mask in (below, ~below):
        part = data.subset(mask)
        if data.noise_sd_estimated and part.replicates is not None:
            part = CalibrationData(
                part.inputs,
                part.y,
                replicates=part.replicates,
                output_name=part.output_name,
                source=part.source,
            )
        parts.append(part)
    return parts[0], parts[1]


def formulations() -> dict[str, Discrepancy]:
    """M0–M4 with discrepancy means (and M3's log-variance) linear in the height.

    For a small drag the excess fall time grows like ``h`` (linear drag) to ``h^{3/2}``
    (quadratic drag), and starting a stopwatch or a release mechanism adds a constant
    offset; ``a + b h`` covers the offset and the linear trend with two coefficients,
    and stays identifiable next to ``g`` because ``∂t/∂g ∝ sqrt(h)`` is not in the span
    of ``{1, h}`` (:func:`kohpymc.check_formulation` confirms rank 3 of 3 for M3).
    M3's log-variance is linear in ``h`` as well: the replicate scatter grows with the
    height (pooled sd 0.054 s below the gap, 0.088 s above).  M4's squared-exponential
    kernel is on the height, with the same linear mean.

    Below the gap the drag excess (+0.011 ± 0.009 s on average) is smaller than the
    replicate scatter, and these generic forms learn a discrepancy that extrapolates the
    wrong way: in our run (4 × 1000 draws, seed 2026, ``notebooks/03_falling_ball.ipynb``)
    every ``G + δ`` of M1–M4 fell below drag-free fall at 9.81 m/s² above the gap, and μ_r
    was 0.58 for M0, 0.45 for M1 and M2 and 0.37 for M3 and M4.  M3's log-variance slope
    is barely constrained and is extrapolated up to 5.7 calibration standard deviations,
    so a few draws have σ_δ of seconds: summarise its predictions by medians.

    Examples
    --------
    >>> list(formulations())
    ['M0', 'M1', 'M2', 'M3', 'M4']
    """
    from kohpymc.discrepancy import (
        ConstantBias,
        GaussianProcess,
        IIDGaussian,
        InputDependentGaussian,
        NoDiscrepancy,
    )

    return {
        "M0": NoDiscrepancy(),
        "M1": ConstantBias(),
        "M2": IIDGaussian(),
        "M3": InputDependentGaussian(mean=["height_m"], log_variance=["height_m"]),
        "M4": GaussianProcess(["height_m"], mean=["height_m"]),
    }
