"""The stand-in as a :class:`~kohpymc.PhysicsModel` and its least-squares fit to data."""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import Any, Literal

import numpy as np

from kohpymc.data import CalibrationData
from kohpymc.examples.dielectric.constants import PRIOR_RANGES
from kohpymc.examples.dielectric.current import (
    charging_current,
    charging_current_jacobian,
    charging_current_sensitivities,
)
from kohpymc.initialization import multistart_least_squares
from kohpymc.physics import PhysicsModel
from kohpymc.priors import Uniform


def physics_model(
    gradient: Literal["analytic", "central", "forward"] = "analytic", *, vectorized: bool = False
) -> PhysicsModel:
    """The stand-in with the uniform priors of Table 3.

    Parameters
    ----------
    gradient : {"analytic", "central", "forward"}
        ``"analytic"`` (default): the exact sensitivities of the semi-analytic solution,
        :func:`charging_current_sensitivities` (about 2 model runs' cost; closer to the
        exact derivative, ~5e-6 relative, than finite differences of the discretised
        model, ~8e-5).  ``"central"`` / ``"forward"``: finite differences (14 / 8 model
        runs; at a least-squares fit the two agree to ~1e-6 relative).
    vectorized : bool
        With finite differences: compute them with :func:`charging_current_jacobian`
        (all perturbed parameter sets in one call, identical values, ~15 % cheaper)
        instead of one model call per perturbation.

    Examples
    --------
    >>> physics_model().parameter_names
    ('ln_NT', 'phi_B', 'ln_sigma', 'ln_gamma', 'eps_inf', 'm_eff', 'E_A')
    >>> physics_model().jacobian is not None, physics_model("central").jacobian is None
    (True, True)
    """
    if gradient not in ("analytic", "central", "forward"):
        raise ValueError(f"gradient must be 'analytic', 'central' or 'forward', got {gradient!r}")
    if gradient == "analytic":
        jacobian = analytic_jacobian
    elif vectorized:
        jacobian = partial(charging_current_jacobian, scheme=gradient)
    else:
        jacobian = None
    return PhysicsModel(
        charging_current,
        {name: Uniform(*bounds) for name, bounds in PRIOR_RANGES.items()},
        inputs=["V", "T", "t"],
        jacobian=jacobian,
        fd_scheme="central" if gradient == "analytic" else gradient,
        name="dielectric_charging",
    )


def analytic_jacobian(inputs: Mapping[str, Any], params: Mapping[str, float]) -> np.ndarray:
    """``∂J/∂θ`` (n, 7) from :func:`charging_current_sensitivities` (the Jacobian only)."""
    return charging_current_sensitivities(inputs, params)[1]


def least_squares_fit(
    data: CalibrationData,
    *,
    n_starts: int = 8,
    seed: int = 0,
    margin: float = 1e-3,
) -> dict[str, float]:
    """Least-squares fit of the stand-in to data, from several starts in the Table 3 box.

    A starting point for samplers: the output varies over ~26 orders of magnitude
    across the box and is nearly flat in the trap parameters at its centre, so a
    sampler started at the prior centre does not find the data.  The fit does not use
    :data:`TRUE_PARAMS`.

    A call of :func:`kohpymc.initialization.multistart_least_squares` on
    :func:`physics_model`: each start (a scrambled Sobol point of the box, scaled to the
    unit cube) is first fitted on log currents, ``ln max(G, 1e-300) - ln max(y, σ)``,
    which is well scaled wherever the current is, then the best log fit is refined on
    the currents themselves, ``(G - y) / σ`` (stage one stops at relative tolerances
    1e-4, stage two at SciPy's defaults).  Both stages use
    :func:`scipy.optimize.least_squares` (trust region reflective, 2-point differences)
    inside the box shrunk by ``margin`` × its width on each side, so the result is
    strictly inside the prior support and can be passed as ``initvals`` even where the
    fit runs into a bound.

    Parameters
    ----------
    data : CalibrationData
        Measurements with inputs ``V``, ``T``, ``t`` (e.g. the calibration half of
        :func:`generate_data`).
    n_starts : int
        Number of starting points (rounded up to a power of two by the Sobol design).
    seed : int
        Seed of the Sobol scrambling.
    margin : float
        Fraction of each parameter's prior width kept clear of the bounds, in [0, 0.5).

    Returns
    -------
    dict
        Parameter name -> fitted value, in the order of :data:`PRIOR_RANGES`.

    Examples
    --------
    >>> from kohpymc.examples.dielectric import (NOISE_SD, PRIOR_RANGES, generate_data,
    ...                                         split_calibration_validation)
    >>> cal, _ = split_calibration_validation(generate_data(seed=1))
    >>> fit = least_squares_fit(cal, n_starts=2)
    >>> list(fit) == list(PRIOR_RANGES)
    True
    >>> rms = np.sqrt(np.mean((charging_current(cal.inputs, fit) - cal.y) ** 2))
    >>> bool(rms < 10 * NOISE_SD)
    True
    """
    if n_starts < 1:
        raise ValueError(f"n_starts must be >= 1, got {n_starts}")
    y = np.asarray(data.y, dtype=float)
    floor = float(data.noise_sd) if data.noise_sd is not None else float(np.std(y)) or 1.0
    result = multistart_least_squares(
        physics_model(),
        data,
        starts=n_starts,
        seed=seed,
        transform=_log_current,
        data_transform=lambda values: np.log(np.maximum(values, floor)),
        margin=margin,
    )
    return result.params


def _log_current(values: np.ndarray) -> np.ndarray:
    """``ln G`` of model currents, floored at 1e-300 so that no current is flat."""
    return np.log(np.maximum(values, 1e-300))
