"""Discovery per output: :func:`kohpymc.discover` run on each output on its own.

Each output's physics ``G_k(x; θ)`` is a :class:`~kohpymc.PhysicsModel`, so the
single-output discovery (where the model fails, which named term is missing, the gap
before and after) runs unchanged on each output's calibration and validation rows with
that output's tolerance.  θ is calibrated per output inside each discovery, not jointly:
a term missing from one output is looked for in that output's residuals.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from kohpymc.discovery import DiscoveryReport, discover
from kohpymc.multi_output.data import MultiOutputData, per_output
from kohpymc.multi_output.physics import MultiOutputPhysics

__all__ = ["discover_outputs"]


def discover_outputs(
    physics: MultiOutputPhysics,
    calibration: MultiOutputData,
    validation: MultiOutputData,
    *,
    tolerance: float | Mapping[str, float],
    outputs: Sequence[str] | None = None,
    **options: Any,
) -> dict[str, DiscoveryReport]:
    """Run :func:`kohpymc.discover` on every output (or the named ones).

    Parameters
    ----------
    physics : MultiOutputPhysics
    calibration, validation : MultiOutputData
    tolerance : float or mapping output -> float
        ε per output, in its units.
    outputs : sequence of str, optional
        Outputs to examine; default all of ``calibration``.
    **options :
        Passed to :func:`kohpymc.discover` for every output (``units`` may be a mapping
        output -> units table).

    Returns
    -------
    dict of str to DiscoveryReport

    Examples
    --------
    >>> reports = discover_outputs(physics, cal, val,
    ...                            tolerance={"u": 0.75, "strain": 7.5})  # doctest: +SKIP
    >>> reports["u"].found  # doctest: +SKIP
    True
    """
    chosen = list(calibration.outputs if outputs is None else outputs)
    tolerances = per_output(tolerance, calibration.outputs, "tolerance")
    units = options.pop("units", None)
    per_units = (
        per_output(units, calibration.outputs, "units")
        if isinstance(units, Mapping) and set(units) <= set(calibration.outputs)
        else dict.fromkeys(calibration.outputs, units)
    )
    reports = {}
    for name in chosen:
        if tolerances[name] is None:
            raise KeyError(f"tolerance gives no value for output {name!r}")
        reports[name] = discover(
            physics.output(name),
            calibration[name],
            validation[name],
            tolerance=tolerances[name],
            units=per_units[name],
            **options,
        )
    return reports
