"""Input checks shared by the API, study files, studies and discovery (one place).

Every check raises with a message naming the data file (when known) and what is wrong,
before any sampling.  The study-file reader adds the file and key on top.
"""

from __future__ import annotations

import math
import re
from typing import Any

from kohpymc.data import CalibrationData
from kohpymc.physics import PhysicsModel

__all__ = [
    "COMPILE_MODES",
    "check_compile_mode",
    "check_execution",
    "check_scheduler",
    "check_workers",
    "check_sampler",
    "check_tolerance",
    "check_physics_runs",
    "check_validation_data",
    "check_count",
]

#: PyTensor compile modes for the log density of PyMC's NUTS
COMPILE_MODES = ("NUMBA", "FAST_RUN")


def _where(data: CalibrationData) -> str:
    return f" ({data.source})" if data.source else ""


def check_tolerance(tolerance: Any) -> float:
    """ε of the reliability metric as a float, or ``ValueError``.

    Examples
    --------
    >>> check_tolerance(0.5)
    0.5
    >>> check_tolerance(-1)
    Traceback (most recent call last):
    ...
    ValueError: validation tolerance must be a positive number, got -1
    """
    ok = isinstance(tolerance, int | float) and not isinstance(tolerance, bool)
    if not ok or not math.isfinite(tolerance) or tolerance <= 0:
        raise ValueError(f"validation tolerance must be a positive number, got {tolerance!r}")
    return float(tolerance)


def check_physics_runs(physics: PhysicsModel, data: CalibrationData, what: str) -> None:
    """The data have the physics inputs and the model runs there at the prior mean.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> check_physics_runs(beam.physics_model(), beam.generate_data(seed=1), "calibration")
    """
    missing = [k for k in physics.inputs if k not in data.inputs]
    if missing:
        raise KeyError(
            f"{what} data{_where(data)} lack input column(s) {missing} of the physics model "
            f"{physics.name!r}"
        )
    try:
        physics.evaluate({k: data.inputs[k] for k in physics.inputs}, physics.prior_mean())
    except Exception as err:
        raise ValueError(
            f"{what} data{_where(data)}: the physics model {physics.name!r} fails on the "
            f"{what} inputs: {err}"
        ) from err


def check_validation_data(
    physics: PhysicsModel, validation: CalibrationData, tolerance: Any
) -> float:
    """Tolerance, non-empty validation data, physics running on them; returns ε.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> check_validation_data(beam.physics_model(), beam.generate_data(seed=2), 0.75)
    0.75
    """
    eps = check_tolerance(tolerance)
    if validation.n == 0:
        raise ValueError(f"validation data{_where(validation)} are empty")
    check_physics_runs(physics, validation, "validation")
    return eps


#: the samplers :func:`kohpymc.calibrate` accepts
SAMPLERS = ("nutpie", "pymc", "smc")


def check_sampler(sampler: Any) -> None:
    """Raise ``ValueError`` unless ``sampler`` is None or one of :data:`SAMPLERS`.

    Examples
    --------
    >>> check_sampler("nutpie")
    """
    if sampler is not None and sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {list(SAMPLERS)}, got {sampler!r}")


def check_compile_mode(mode: Any) -> None:
    """``mode`` is ``None`` or one of :data:`COMPILE_MODES`.

    Examples
    --------
    >>> check_compile_mode("NUMBA")
    """
    if mode is not None and mode not in COMPILE_MODES:
        raise ValueError(f"mode must be one of {list(COMPILE_MODES)} or None, got {mode!r}")


#: a Dask scheduler address: ``tcp://host:port`` (or ``tls://``, ``ucx://``, ...)
_ADDRESS = re.compile(r"^([a-z][a-z0-9+.-]*://)?[^\s:/]+(:\d+)?$|^[a-z]+://\[[0-9a-f:]+\](:\d+)?$")


def check_workers(workers: Any) -> int:
    """The number of worker processes, a positive integer.

    Examples
    --------
    >>> check_workers(2)
    2
    >>> check_workers(0)
    Traceback (most recent call last):
    ...
    ValueError: workers must be a positive integer, got 0
    """
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    return workers


def check_scheduler(scheduler: Any) -> None:
    """``None``, a Dask scheduler address such as ``"tcp://10.0.0.5:8786"``, or a client.

    Examples
    --------
    >>> check_scheduler("tcp://10.0.0.5:8786")
    >>> check_scheduler("a b")
    Traceback (most recent call last):
    ...
    ValueError: scheduler must be a Dask scheduler address like 'tcp://HOST:PORT', got 'a b'
    """
    if scheduler is None or type(scheduler).__name__ == "Client":
        return
    if not isinstance(scheduler, str) or not _ADDRESS.match(scheduler):
        raise ValueError(
            f"scheduler must be a Dask scheduler address like 'tcp://HOST:PORT', got {scheduler!r}"
        )


def check_execution(workers: Any, scheduler: Any) -> None:
    """Where tasks run: ``workers`` processes started here, or an existing ``scheduler``.

    Examples
    --------
    >>> check_execution(1, "tcp://10.0.0.5:8786")
    >>> check_execution(4, "tcp://10.0.0.5:8786")
    Traceback (most recent call last):
    ...
    ValueError: give workers (a local cluster) or scheduler (an existing cluster), not both
    """
    check_workers(workers)
    check_scheduler(scheduler)
    if workers > 1 and scheduler is not None:
        raise ValueError(
            "give workers (a local cluster) or scheduler (an existing cluster), not both"
        )


def check_count(value: Any, name: str, *, minimum: int = 1) -> int:
    """``value`` as an integer ``>= minimum`` (a count, a seed), or ``ValueError`` naming it.

    Examples
    --------
    >>> check_count(200, "replicates")
    200
    >>> check_count(0, "draws")
    Traceback (most recent call last):
    ...
    ValueError: draws must be an integer >= 1, got 0
    """
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return value
