"""A slow simulator: heat conduction through a plate, with a sleep standing in for the solver.

A plate of thickness :data:`THICKNESS_MM` (10 mm), initially at :data:`INITIAL_C` (20 °C)
throughout, has its front face brought to a temperature ``T_s`` (°C) at ``t = 0``; its
back face is insulated and carries a thermocouple.  The back-face temperature is the
series solution of the 1-D heat equation

    T(t) = T_s + (T_0 − T_s) Σₙ 4 (−1)ⁿ / ((2n + 1) π) · exp(−λₙ² α t / L²),
    λₙ = (2n + 1) π / 2,

with the thermal diffusivity ``α`` (mm²/s) and ``T_s`` unknown:
``alpha ~ Uniform(1, 10)`` mm²/s (stainless to carbon steel) and
``T_s ~ Uniform(60, 140)`` °C.

**The sleep is the cost.**  The series takes microseconds; :func:`slab_temperature` then
sleeps :data:`DEFAULT_SECONDS` (1 s) per call, a documented stand-in for a finite-element
run of the same plate, which returns the whole temperature history (every requested time)
from one solve.  So one call = one θ = one second, whatever the number of times asked for
— as :func:`kohpymc.emulator.run_design` sends "runs sharing θ to one simulator call".
The sleep is set per call (``seconds=``) or by the environment variable
``KOHPYMC_SLOW_SIMULATOR_SECONDS`` (read at each call, so Dask workers started from a
shell that sets it inherit it).  ``log=`` (or ``KOHPYMC_SLOW_SIMULATOR_LOG``) appends
one line per call to a file, to count calls across worker processes.

The synthetic data of ``slow_simulator_study.toml`` are :func:`generate_data` with
:data:`TRUE_ALPHA`, :data:`TRUE_TS` and noise sd :data:`NOISE_SD`;
:func:`write_study` writes a variant of the study (another sleep, a call log, with or
without the emulator) for the benchmark ``benchmarks/slow_simulator.py`` and the tests.
No Jacobian is given (a finite-element solver rarely has one): a direct calibration
differentiates it by central finite differences, ``2p = 4`` more calls per gradient.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.physics import PhysicsModel
from kohpymc.priors import Uniform

__all__ = [
    "CALIBRATION_TIMES",
    "DEFAULT_SECONDS",
    "INITIAL_C",
    "NOISE_SD",
    "STUDY_FILE",
    "THICKNESS_MM",
    "TRUE_ALPHA",
    "TRUE_TS",
    "VALIDATION_TIMES",
    "back_face_temperature",
    "generate_data",
    "physics_model",
    "slab_temperature",
    "write_study",
]

THICKNESS_MM = 10.0  # plate thickness L, mm
INITIAL_C = 20.0  # initial temperature T_0, °C
TRUE_ALPHA = 4.2  # thermal diffusivity, mm²/s (a stainless steel)
TRUE_TS = 100.0  # front-face temperature, °C
NOISE_SD = 0.5  # thermocouple noise sd, °C
DEFAULT_SECONDS = 1.0  # the stand-in cost of one simulator call, s
#: 20 times, 3 to 60 s every 3 s
CALIBRATION_TIMES = tuple(float(t) for t in np.arange(3.0, 61.0, 3.0))
#: 6 times between the calibration times (inside the emulator's box)
VALIDATION_TIMES = (4.5, 13.5, 22.5, 31.5, 40.5, 49.5)
#: the study file of this example
STUDY_FILE = Path(__file__).with_name("slow_simulator_study.toml")
_TERMS = 60  # series terms: the first neglected one is < 1e-30 at t = 3 s, α = 1


def back_face_temperature(t: Any, alpha: float, ts: float) -> np.ndarray:
    """The series solution at the insulated back face (no sleep), °C.

    Examples
    --------
    >>> back_face_temperature([0.0, 1e6], 4.2, 100.0).round(3)
    array([ 20., 100.])
    """
    t = np.asarray(t, dtype=float)
    n = np.arange(_TERMS)
    lam = (2 * n + 1) * np.pi / 2
    coef = 4 * (-1.0) ** n / ((2 * n + 1) * np.pi)
    decay = np.exp(-np.multiply.outer(alpha * t / THICKNESS_MM**2, lam**2))
    series = decay @ coef
    # at t = 0 the truncated alternating series is not yet 1: the plate is at T_0 there
    series = np.where(t <= 0.0, 1.0, series)
    return ts + (INITIAL_C - ts) * series


def slab_temperature(
    inputs: Mapping[str, Any],
    params: Mapping[str, Any],
    *,
    seconds: float | None = None,
    log: str | os.PathLike[str] | None = None,
) -> np.ndarray:
    """The simulator: back-face temperature at ``inputs["t"]`` (s), after a sleep.

    Parameters
    ----------
    inputs : mapping
        ``{"t": times in s}`` (all times of one call come from one "solve").
    params : mapping
        ``{"alpha": mm²/s, "Ts": °C}``.
    seconds : float, optional
        The sleep per call; default ``$KOHPYMC_SLOW_SIMULATOR_SECONDS`` or
        :data:`DEFAULT_SECONDS`.
    log : path, optional
        Append one line per call (pid and θ) to this file; default
        ``$KOHPYMC_SLOW_SIMULATOR_LOG`` if set.

    Examples
    --------
    >>> slab_temperature({"t": [3.0, 60.0]}, {"alpha": 4.2, "Ts": 100.0}, seconds=0).round(2)
    array([27.42, 99.8 ])
    """
    if seconds is None:
        seconds = float(os.environ.get("KOHPYMC_SLOW_SIMULATOR_SECONDS", DEFAULT_SECONDS))
    if log is None:
        log = os.environ.get("KOHPYMC_SLOW_SIMULATOR_LOG") or None
    if seconds < 0:
        raise ValueError(f"slab_temperature: seconds must be >= 0, got {seconds}")
    out = back_face_temperature(inputs["t"], float(params["alpha"]), float(params["Ts"]))
    if seconds:
        time.sleep(seconds)
    if log is not None:
        line = f"{os.getpid()} {float(params['alpha'])!r} {float(params['Ts'])!r}\n"
        with open(log, "a") as f:  # one short append per call: safe across processes
            f.write(line)
    return out


def physics_model(seconds: float | None = None) -> PhysicsModel:
    """The plate model with its uniform priors; ``seconds`` fixes the sleep per call.

    Examples
    --------
    >>> physics_model(seconds=0).parameter_names
    ('alpha', 'Ts')
    """
    priors = {"alpha": Uniform(1.0, 10.0), "Ts": Uniform(60.0, 140.0)}

    def sleeping(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
        return slab_temperature(inputs, params, seconds=seconds)

    function = slab_temperature if seconds is None else sleeping
    return PhysicsModel(function, priors, inputs=["t"], name="slab_temperature")


def generate_data(
    times: Sequence[float] = CALIBRATION_TIMES,
    *,
    seed: int = 0,
    alpha: float = TRUE_ALPHA,
    ts: float = TRUE_TS,
    noise_sd: float = NOISE_SD,
) -> CalibrationData:
    """Synthetic thermocouple readings: the series plus ``N(0, noise_sd²)``, to 4 decimals.

    Examples
    --------
    >>> data = generate_data(seed=2026)
    >>> data.n, data.output_name
    (20, 'T_back')
    """
    t = np.asarray(times, dtype=float)
    rng = np.random.default_rng(seed)
    y = back_face_temperature(t, alpha, ts) + rng.normal(0.0, noise_sd, size=t.size)
    return CalibrationData(pd.DataFrame({"t": t}), np.round(y, 4), output_name="T_back")


_WRAPPER = '''"""Written by kohpymc.examples.slow_simulator.write_study."""
from kohpymc.examples.slow_simulator import slab_temperature


def model(inputs, params):
    return slab_temperature(inputs, params, seconds={seconds!r}, log={log!r})
'''


def write_study(
    folder: str | os.PathLike[str],
    *,
    seconds: float = DEFAULT_SECONDS,
    log: str | os.PathLike[str] | None = None,
    emulator: bool = True,
    runs: int | None = None,
    sampling: Mapping[str, int] | None = None,
) -> Path:
    """A copy of ``slow_simulator_study.toml`` in ``folder`` with another sleep or call log.

    Writes ``folder/simulator.py`` (calling :func:`slab_temperature` with ``seconds`` and
    ``log`` fixed) and ``folder/study.toml`` (the shipped study with absolute data paths,
    this function, ``[emulator]`` dropped unless ``emulator``, ``runs`` and ``[sampling]``
    values replaced when given).

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc import load_study
    >>> path = write_study(tempfile.mkdtemp(), seconds=0.0, emulator=False)
    >>> spec = load_study(path)
    >>> spec.emulator is None, spec.calibration.n
    (True, 20)
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    log_text = None if log is None else str(Path(log).resolve())
    (folder / "simulator.py").write_text(_WRAPPER.format(seconds=float(seconds), log=log_text))
    data = STUDY_FILE.parent / "data"
    lines = []
    section = None
    for line in STUDY_FILE.read_text().splitlines():
        stripped = line.strip()
        if stripped.startswith("["):
            section = stripped.strip("[]")
        if section == "emulator" and not emulator:
            continue
        key = stripped.split("=")[0].strip() if "=" in stripped else None
        if section == "physics" and key == "function":
            line = 'function = "simulator.py:model"'
        elif section == "data" and key in ("calibration", "validation"):
            line = f'{key} = "{(data / f"slow_simulator_{key}.csv").as_posix()}"'
        elif section == "emulator" and key == "runs" and runs is not None:
            line = f"runs = {int(runs)}"
        elif section == "sampling" and sampling and key is not None and key in sampling:
            line = f"{key} = {int(sampling[key])}"
        lines.append(line)
    path = folder / "study.toml"
    path.write_text("\n".join(lines) + "\n")
    return path
