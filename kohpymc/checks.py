"""Input checks shared by the API, study files, studies and discovery (one place).

Every check raises with a message naming the data file (when known) and what is wrong,
before any sampling.  The study-file reader adds the file and key on top.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from kohpymc.data import MAX_ABS_VALUE, CalibrationData
from kohpymc.physics import PhysicsModel

__all__ = [
    "COMPILE_MODES",
    "FormulationBuildError",
    "JacobianError",
    "check_compile_mode",
    "check_execution",
    "check_scheduler",
    "check_workers",
    "check_sampler",
    "check_tolerance",
    "check_physics_runs",
    "check_validation_data",
    "check_count",
    "check_formulations_build",
    "check_label",
    "check_output_path",
    "check_positive_number",
    "check_target_accept",
    "check_validation_weights",
    "resolve_sampler",
]

#: PyTensor compile modes for the log density of PyMC's NUTS
COMPILE_MODES = ("NUMBA", "FAST_RUN")


class JacobianError(ValueError):
    """The user's Jacobian of the physics model fails where the model itself runs."""


class FormulationBuildError(ValueError):
    """A formulation's model cannot be composed on the data; ``label`` names it."""

    def __init__(self, label: str, message: str) -> None:
        super().__init__(message)
        self.label = label


def _where(data: Any) -> str:
    source = getattr(data, "source", None)
    return f" ({source})" if source else ""


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


def check_physics_model(physics: Any) -> PhysicsModel:
    """``physics`` if it is a :class:`~kohpymc.PhysicsModel`, else a ``TypeError``.

    The error says what to pass: an emulator (``kp.emulate(...)``) is not a physics
    model, its ``physics_model()`` is; a bare function needs wrapping.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> check_physics_model(beam.physics_model()).name
    'euler_bernoulli'
    >>> check_physics_model(beam.euler_bernoulli)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    TypeError: physics must be a kohpymc.PhysicsModel, got function: wrap it as ...
    """
    if isinstance(physics, PhysicsModel):
        return physics
    kind = type(physics).__name__
    if callable(getattr(physics, "physics_model", None)):
        raise TypeError(
            f"physics must be a kohpymc.PhysicsModel, got an {kind}: pass its "
            "physics_model() (the emulator as a physics model, its uncertainty in the likelihood)"
        )
    raise TypeError(
        f"physics must be a kohpymc.PhysicsModel, got {kind}: wrap it as "
        "kp.PhysicsModel(function, priors, inputs=[...])"
    )


def check_physics_runs(physics: PhysicsModel, data: CalibrationData, what: str) -> None:
    """The data have the physics inputs; the model (and its Jacobian) run there at the prior mean.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> check_physics_runs(beam.physics_model(), beam.generate_data(seed=1), "calibration")
    """
    check_physics_model(physics)
    missing = [k for k in physics.inputs if k not in data.inputs]
    if missing:
        raise KeyError(
            f"{what} data{_where(data)} lack input column(s) {missing} of the physics model "
            f"{physics.name!r}"
        )
    inputs = {k: data.inputs[k] for k in physics.inputs}
    try:
        centre = physics.regular_point(inputs)  # the prior centre unless singular there
        output = np.asarray(physics.evaluate(inputs, centre), dtype=float)
    except (Exception, SystemExit) as err:  # SystemExit: a function calling sys.exit()
        raise ValueError(
            f"{what} data{_where(data)}: the physics model {physics.name!r} fails on the "
            f"{what} inputs: {err}"
        ) from err
    if output.size and np.max(np.abs(output)) > MAX_ABS_VALUE:
        raise ValueError(
            f"{what} data{_where(data)}: the physics model {physics.name!r} returns "
            f"{np.max(np.abs(output)):.3g} at the prior centre; values beyond "
            f"±{MAX_ABS_VALUE:.0e} overflow when squared (check the units and the priors)"
        )
    if physics.jacobian is None:
        return
    try:
        physics.jacobian_matrix(inputs, centre)
    except (Exception, SystemExit) as err:
        raise JacobianError(
            f"{what} data{_where(data)}: the Jacobian of {physics.name!r} fails on the "
            f"{what} inputs: {err}"
        ) from err


def check_formulations_build(
    physics: Any,
    data: Any,
    formulations: Mapping[str, Any],
    compose: Callable[..., Any] | None = None,
) -> None:
    """Each formulation's model composes on the calibration data (nothing compiled or sampled).

    Raises :class:`FormulationBuildError` naming the first formulation that does not (a
    grid GP on data that are not a grid, an input the data lack, ...).  ``compose``
    builds one model (default :func:`kohpymc.model.compose_model`; a multi-output study
    passes :func:`kohpymc.multi_output.compose_multi_output_model`).

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> check_formulations_build(beam.physics_model(), beam.generate_data(seed=1),
    ...                          beam.formulations())
    """
    from kohpymc.model import compose_model

    compose = compose_model if compose is None else compose
    for label, formulation in formulations.items():
        try:
            compose(physics, data, formulation)
        except Exception as err:  # noqa: BLE001 - any failure is this formulation's
            raise FormulationBuildError(
                label,
                f"{label} cannot be built on the calibration data{_where(data)}: "
                f"{type(err).__name__}: {err}",
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


#: the samplers :func:`kohpymc.calibrate` accepts, and the older ``method`` spellings
SAMPLERS = ("nutpie", "pymc", "smc")
METHODS = ("nuts", "smc")


def check_sampler(sampler: Any, key: str = "sampler") -> None:
    """Raise ``ValueError`` unless ``sampler`` is None or one of :data:`SAMPLERS`.

    With ``key="method"``, the older spelling: one of :data:`METHODS`.

    Examples
    --------
    >>> check_sampler("nutpie")
    >>> check_sampler("hmc", "method")
    Traceback (most recent call last):
    ...
    ValueError: method must be one of ['nuts', 'smc'], got 'hmc'
    """
    allowed = METHODS if key == "method" else SAMPLERS
    if sampler is not None and sampler not in allowed:
        raise ValueError(f"{key} must be one of {list(allowed)}, got {sampler!r}")


def resolve_sampler(sampler: Any, method: Any = None, nuts_sampler: Any = None) -> str | None:
    """The sampler from ``sampler`` or its older spellings ``method`` / ``nuts_sampler``.

    Raises ``ValueError`` for an unknown name or spellings that contradict each other.

    Examples
    --------
    >>> resolve_sampler(None, method="smc")
    'smc'
    >>> resolve_sampler("pymc", method="smc")
    Traceback (most recent call last):
    ...
    ValueError: sampler='pymc' contradicts method/nuts_sampler='smc'
    """
    check_sampler(sampler)
    check_sampler(method, "method")
    if nuts_sampler not in (None, "pymc", "nutpie"):
        raise ValueError(f"nuts_sampler must be 'pymc' or 'nutpie', got {nuts_sampler!r}")
    older = "smc" if method == "smc" else nuts_sampler
    if sampler is not None and older is not None and older != sampler:
        raise ValueError(f"sampler={sampler!r} contradicts method/nuts_sampler={older!r}")
    return sampler or older


def check_target_accept(value: Any) -> float:
    """NUTS's target acceptance rate, a number strictly between 0 and 1.

    Examples
    --------
    >>> check_target_accept(0.9)
    0.9
    >>> check_target_accept(1)
    Traceback (most recent call last):
    ...
    ValueError: target_accept must be a number in (0, 1), got 1
    """
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not ok or not 0 < value < 1:
        raise ValueError(f"target_accept must be a number in (0, 1), got {value!r}")
    return float(value)


#: a formulation label: it names files (``<label>.nc``) and table rows
_LABEL = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}$")
#: labels the output folder uses for itself
RESERVED_LABELS = ("combined",)


def check_label(label: Any) -> str:
    """A formulation label: letters, digits, ``_.+-``, not one kohpymc uses itself.

    Examples
    --------
    >>> check_label("M3b")
    'M3b'
    >>> check_label("../M3")
    Traceback (most recent call last):
    ...
    ValueError: label '../M3': use 1-64 letters, digits and _.+- (it names a file)
    """
    if not isinstance(label, str) or not _LABEL.match(label):
        raise ValueError(f"label {label!r}: use 1-64 letters, digits and _.+- (it names a file)")
    if label.lower() in RESERVED_LABELS:
        raise ValueError(f"label {label!r} is reserved for the weighted mixture")
    return label


def check_validation_weights(weights: Any, n: int) -> np.ndarray:
    """Weights of the validation points in μ_r (Eq. 22): ``n`` finite values ``>= 0``, not all 0.

    Examples
    --------
    >>> check_validation_weights([1, 2], 2)
    array([1., 2.])
    >>> check_validation_weights([1, -2], 2)
    Traceback (most recent call last):
    ...
    ValueError: validation weights must be finite and >= 0 (row 1 is -2.0)
    """
    try:
        values = np.asarray(weights, dtype=float).reshape(-1)
    except (TypeError, ValueError) as err:
        raise ValueError(f"validation weights are not numeric: {err}") from err
    if values.size != n:
        raise ValueError(f"{values.size} validation weights for {n} validation rows")
    bad = np.flatnonzero(~np.isfinite(values) | (values < 0))
    if bad.size:
        first = int(bad[0])
        raise ValueError(
            f"validation weights must be finite and >= 0 (row {first} is {float(values[first])!r})"
        )
    if not values.sum() > 0:
        raise ValueError("validation weights are all 0")
    return values


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


def check_positive_number(value: Any, name: str) -> float:
    """``value`` as a finite float ``> 0`` (not a bool), or ``ValueError`` naming it.

    Examples
    --------
    >>> check_positive_number(0.3, "noise_sd")
    0.3
    >>> check_positive_number(float("nan"), "noise_sd")
    Traceback (most recent call last):
    ...
    ValueError: noise_sd must be a positive finite number, got nan
    """
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def check_output_path(path: str | os.PathLike[str], *, folder: bool = True) -> None:
    """An output folder (``folder=True``) or file that can be written: checked, not created.

    Raises ``ValueError`` when a folder on the way (or the output folder itself) is an
    existing file, an output file is an existing folder, or the nearest existing folder is
    not writable.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> base = pathlib.Path(tempfile.mkdtemp())
    >>> check_output_path(base / "results")
    >>> (base / "taken").write_text("a file")
    6
    >>> check_output_path(base / "taken" / "results")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: output path .../taken/results: .../taken is a file, not a folder
    """
    text = os.fspath(path)
    if not text or "\x00" in text:
        raise ValueError(f"output path {text!r} is not a usable path")
    target = Path(text)
    if not folder and target.is_dir():
        raise ValueError(f"output file {target} is a folder")
    for above in (target, *target.parents) if folder else target.parents:
        if above.is_dir():
            if not os.access(above, os.W_OK | os.X_OK):
                raise ValueError(f"output path {target}: folder {above} is not writable")
            return
        if above.exists():
            raise ValueError(f"output path {target}: {above} is a file, not a folder")
