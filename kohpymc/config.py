"""Scripted studies: read a study from a TOML file.

A study file names the physics function, its inputs, output and parameter priors, the
calibration and validation CSV files, the validation tolerance and, optionally, the
formulations and sampler settings::

    [physics]
    function = "physics.py:model"     # file relative to this TOML, or "module:function"
    inputs = ["x", "P"]
    output = "u"
    # jacobian = "physics.py:model_jacobian"   # optional, same syntax
    # time = "t"                               # optional: adds M5 to the defaults
    [physics.parameters]
    E = { prior = "uniform", lower = 50, upper = 300 }

    [data]
    calibration = "calib.csv"
    validation = "valid.csv"
    noise_sd = 0.316                  # optional; else from replicates, else calibrated
    # replicates = "inputs"           # optional: rows with equal inputs are replicates
    # [data.units]                    # optional (discover): x = "mm", P = "kN", output = "um"

    [validation]
    tolerance = 0.75
    # weights = "w"                   # optional column of the validation CSV (Eq. 22)

    [formulations]                    # optional; default M0–M4 (M5 with physics.time)
    M0 = "none"
    M3 = { type = "input_dependent", mean = ["x"], log_variance = ["x"] }
    M4 = { type = "gp", inputs = ["x"] }

    [sampling]                        # optional
    draws = 1000
    tune = 1000
    chains = 4
    cores = 2                         # chains run in parallel processes (PyMC's default: 1)
    # mode = "NUMBA"                  # PyTensor compile mode of NUTS's log density (see calibrate)
    seed = 2026

    [execution]                       # optional; the CLI's --workers / --scheduler win
    # workers = 2                     # a local Dask cluster of 2 worker processes
    # scheduler = "tcp://10.0.0.5:8786"   # or an existing Dask cluster

    [output]                          # optional; the CLI's --out wins
    dir = "beam_study"

    [emulator]                        # optional: calibrate through a GP emulator
    runs = 200                        # (keys: kohpymc.emulator.study, docs/emulator.md)
    design = "maximin-lhs"
    sequential = 2
    # functional = ["t"]              # a curve per run over these inputs (FunctionalEmulator)

    [check]                           # optional: settings of `kohpymc check` (kohpymc.sbc)
    formulation = "M0"
    replicates = 200
    draws = 400                       # the check's own (shorter) chains
    [check.simulate]                  # optional: a data-generating process that differs
    noise_sd = 0.5                    # from the fitted model, to see the check fail
    parameters = { E = { prior = "uniform", lower = 300, upper = 400 } }

Every problem is reported with the file and the key at fault.  Formulation types are the
registered kinds (:func:`kohpymc.formulation_kinds`: ``none``, ``constant``, ``iid``,
``input_dependent``, ``gp``, ``nonstationary_gp``, ``grid_gp``, ``scaled_gp``, ...); the
other keys of a formulation table are its constructor's options.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import sys
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from kohpymc.checks import (
    JacobianError,
    check_compile_mode,
    check_count,
    check_label,
    check_physics_runs,
    check_positive_number,
    check_sampler,
    check_scheduler,
    check_target_accept,
    check_tolerance,
    check_validation_weights,
    check_workers,
    resolve_sampler,
)
from kohpymc.data import CalibrationData, NoReplicatesError, read_csv_table
from kohpymc.discrepancy import Discrepancy, FormulationSpecError, from_dict
from kohpymc.discrepancy.defaults import default_formulations
from kohpymc.execution import ship_by_value
from kohpymc.physics import PhysicsModel
from kohpymc.priors import as_prior

__all__ = ["CheckSpec", "StudyConfigError", "StudySpec", "load_study"]


class StudyConfigError(ValueError):
    """A study file is wrong; the message names the file and the key."""


#: ``[physics]`` keys passed on to :class:`~kohpymc.PhysicsModel` as they are
PHYSICS_OPTIONS = ("backend", "fd_scheme", "on_nonfinite", "name")

_SECTIONS: dict[str, set[str] | None] = {
    "study": {"name"},
    "physics": {
        "function", "inputs", "output", "parameters", "jacobian", "backend", "fd_scheme",
        "on_nonfinite", "time", "name",
    },
    "data": {"calibration", "validation", "noise_sd", "replicates", "units"},
    "validation": {"tolerance", "weights"},
    "formulations": None,  # free labels
    "sampling": {
        "draws", "tune", "chains", "cores", "workers", "seed", "target_accept", "method", "mode",
        "sampler", "reparameterize",
    },
    "execution": {"workers", "scheduler"},
    "output": {"dir"},
    "emulator": None,  # keys checked by kohpymc.emulator.study.EmulatorSettings
    "check": {
        "formulation", "replicates", "draws", "tune", "chains", "seed", "rank_draws", "simulate",
    },
}  # fmt: skip

_SIMULATE_KEYS = {"parameters", "noise_sd", "sigma_obs"}


@dataclass
class CheckSpec:
    """The ``[check]`` table: settings of ``kohpymc check`` and the data-generating process.

    Settings left out are ``None`` (the command line or ``[sampling]`` decide).  The
    ``simulate_*`` fields describe where simulated data come from when that should differ
    from the fitted model (a deliberately wrong set-up); by default the truth is drawn
    from the fitted model's own prior.

    Attributes
    ----------
    formulation : str or None
        Label of the formulation to check (one of ``[formulations]``).
    replicates, draws, tune, chains, seed, rank_draws : int or None
        Number of simulated data sets, the sampler settings of each fit, the base seed and
        the number of thinned posterior draws a rank is computed among.
    simulate_parameters : dict name -> Prior
        Priors the true physics parameters are drawn from instead of ``[physics.parameters]``.
    simulate_noise_sd : float or None
        Simulate with this fixed noise sd (the fit keeps ``[data] noise_sd`` or calibrates σ).
    simulate_noise_prior : Prior or None
        Draw the simulation's noise sd from this prior instead.
    """

    formulation: str | None = None
    replicates: int | None = None
    draws: int | None = None
    tune: int | None = None
    chains: int | None = None
    seed: int | None = None
    rank_draws: int | None = None
    simulate_parameters: dict[str, Any] = field(default_factory=dict)
    simulate_noise_sd: float | None = None
    simulate_noise_prior: Any = None

    @property
    def simulates_the_fitted_model(self) -> bool:
        """Whether the data-generating process is the fitted model (no override)."""
        return (
            not self.simulate_parameters
            and self.simulate_noise_sd is None
            and (self.simulate_noise_prior is None)
        )


@dataclass
class StudySpec:
    """A study read from a TOML file, ready for :func:`kohpymc.run_study`.

    Attributes
    ----------
    source : Path
        The TOML file.
    physics : PhysicsModel
    calibration, validation : CalibrationData
    tolerance : float
    formulations : dict label -> Discrepancy
    validation_weights : array or None
    sampling : dict
        ``draws``, ``tune``, ``chains``, ``random_seed``, ... for :func:`run_study`.
    execution : dict
        ``workers`` and/or ``scheduler`` for :func:`run_study` (``[execution]``).
    out_dir : Path
        Output folder (``[output] dir`` relative to the file, default
        ``<file stem>_results`` beside it).
    check : CheckSpec
        The ``[check]`` table (``kohpymc check``).
    units : dict or None
        ``[data.units]``: unit strings of inputs and of the output (key ``"output"``),
        read by ``kohpymc discover``.
    emulator : EmulatorSettings or None
        The ``[emulator]`` table: calibrate through a GP emulator of the physics.
    """

    source: Path
    physics: PhysicsModel
    calibration: CalibrationData
    validation: CalibrationData
    tolerance: float
    formulations: dict[str, Discrepancy]
    validation_weights: Any = None
    sampling: dict[str, Any] = field(default_factory=dict)
    out_dir: Path = Path("study_results")
    execution: dict[str, Any] = field(default_factory=dict)
    check: CheckSpec = field(default_factory=CheckSpec)
    units: dict[str, str] | None = None
    emulator: Any = None

    def run_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`kohpymc.run_study` for this study."""
        return {
            "physics": self.physics,
            "calibration": self.calibration,
            "validation": self.validation,
            "formulations": self.formulations,
            "tolerance": self.tolerance,
            "validation_weights": self.validation_weights,
            **self.sampling,
            **self.execution,
        }


def _err(path: Path, key: str, message: str) -> StudyConfigError:
    return StudyConfigError(f"{path}: [{key}] {message}")


def _check_keys(path: Path, where: str, table: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise _err(path, where, f"unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _require(path: Path, table: Mapping[str, Any], section: str, key: str) -> Any:
    if key not in table:
        raise _err(path, f"{section}.{key}", "is required but missing")
    return table[key]


def _load_callable(spec: Any, base: Path, path: Path, key: str) -> Callable[..., Any]:
    """``"file.py:name"`` (relative to ``base``) or ``"package.module:name"``."""
    if not isinstance(spec, str) or ":" not in spec:
        raise _err(
            path, key, f"must look like 'file.py:function' or 'module:function', got {spec!r}"
        )
    target, _, attr = spec.rpartition(":")
    if target.endswith(".py"):
        file = (base / target).resolve()
        if not file.is_file():
            raise _err(path, key, f"file {file} not found")
        name = f"kohpymc_user_{abs(hash(str(file)))}"
        module_spec = importlib.util.spec_from_file_location(name, file)
        if module_spec is None or module_spec.loader is None:
            raise _err(path, key, f"cannot import {file}")
        module = importlib.util.module_from_spec(module_spec)
        sys.modules[name] = module
        try:
            module_spec.loader.exec_module(module)
        except (Exception, SystemExit) as err:  # a script exiting at import is an error too
            sys.modules.pop(name, None)
            raise _err(path, key, f"importing {file} failed: {type(err).__name__}: {err}") from err
        ship_by_value(module)  # Dask workers cannot import it: its functions travel by value
    else:
        try:
            module = importlib.import_module(target)
        except (Exception, SystemExit) as err:
            raise _err(path, key, f"cannot import module {target!r}: {err}") from err
    func = getattr(module, attr, None)
    if not callable(func):
        raise _err(path, key, f"{target!r} has no function {attr!r}")
    return func


def _data(
    path: Path, base: Path, key: str, file: Any, inputs, output, noise_sd, replicates
) -> CalibrationData:
    if not isinstance(file, str):
        raise _err(path, key, f"must be a CSV file name, got {file!r}")
    csv = (base / file).resolve()
    if not csv.is_file():
        raise _err(path, key, f"data file {csv} not found")
    try:
        return CalibrationData.from_csv(
            csv, inputs=inputs, output=output, noise_sd=noise_sd, replicates=replicates
        )
    except (KeyError, ValueError, TypeError) as err:
        raise _err(path, key, str(err).strip("'\"")) from err


def _names(path: Path, key: str, value: Any) -> list[str]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        what = "output column names" if key.endswith("output") else "input names"
        raise _err(path, key, f"must be a list of {what}, got {value!r}")
    repeated = sorted({v for v in value if value.count(v) > 1})
    if repeated:
        raise _err(path, key, f"names {repeated} more than once")
    return list(value)


def _formulation(
    path: Path, label: str, value: Any, inputs: list[str], time: str | None
) -> Discrepancy:
    """One ``[formulations]`` entry through the formulation registry."""
    key = f"formulations.{label}"
    if isinstance(value, dict):
        for name_key in ("mean", "log_variance", "inputs"):
            if name_key in value and not isinstance(value[name_key], dict):
                _names(path, f"{key}.{name_key}", value[name_key])
    try:
        label = check_label(label)
    except ValueError as err:
        raise _err(path, key, str(err)) from err
    try:
        formulation = from_dict(value, inputs=inputs, time=time)
    except FormulationSpecError as err:
        raise _err(path, f"{key}.{err.key}" if err.key else key, str(err)) from err
    absent = [name for name in formulation.inputs if name not in inputs]
    if absent:
        raise _err(
            path, key, f"uses input(s) {absent} that are not physics inputs {inputs} (the data "
            "files are read for the physics inputs and the output only)",
        )  # fmt: skip
    return formulation


def load_study(path: str | Path) -> StudySpec:
    r"""Read and check a study TOML file (see the module docstring for its keys).

    Parameters
    ----------
    path : path
        The TOML file; relative file names inside it are relative to its folder.

    Returns
    -------
    StudySpec

    Raises
    ------
    StudyConfigError
        Naming the file and the key: a file that is not UTF-8 or not TOML, unknown keys,
        missing required keys, values of the wrong type or range, missing or unreadable
        data files (empty, repeated or missing columns, NaN/inf), a function or Jacobian
        that does not import or fails on the data at the prior centre, bad priors and
        formulations (kinds, options, labels, inputs the data lack).  Nothing else.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "s.toml").write_text('[physics]\nfunktion = "m.py:f"\n')
    >>> load_study(d / "s.toml")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kohpymc.config.StudyConfigError: .../s.toml: [physics] unknown key(s) ['funktion']; ...
    """
    path = Path(path)
    doc = _read_document(path)
    base = path.resolve().parent
    physics, inputs, output, time = _physics_section(path, base, doc["physics"])
    calibration, validation = _data_section(path, base, doc["data"], physics, inputs, output)
    tolerance, weights = _validation_section(path, doc["validation"], validation)
    formulations = _formulations_section(path, doc, inputs, time)
    sampling_doc = _sampling_section(path, doc)
    execution = _execution_section(path, doc, sampling_doc.pop("workers", None))
    check = _check_section(path, doc.get("check", {}), physics, formulations)
    out_dir = _output_dir(path, base, doc)
    return StudySpec(
        source=path,
        physics=physics,
        calibration=calibration,
        validation=validation,
        tolerance=float(tolerance),
        formulations=formulations,
        validation_weights=weights,
        sampling=sampling_doc,
        out_dir=out_dir,
        execution=execution,
        check=check,
        units=_units_table(path, doc["data"].get("units"), inputs, output),
        emulator=_emulator_section(path, doc, formulations, inputs),
    )


def _output_dir(path: Path, base: Path, doc: dict) -> Path:
    """``[output] dir`` relative to the file, default ``<file stem>_results`` beside it."""
    out = doc.get("output", {}).get("dir")
    if out is not None and (not isinstance(out, str) or not out or "\x00" in out):
        raise _err(path, "output.dir", f"must be a folder name, got {out!r}")
    return (base / out) if out else base / f"{path.stem}_results"


def _replicates(path: Path, key: str, value: Any) -> str | None:
    """``[data] replicates``: ``"inputs"``, a column name, or absent."""
    if value is not None and (not isinstance(value, str) or not value):
        raise _err(path, key, f'must be "inputs" or a column name, got {value!r}')
    return value


def _weight_column(
    path: Path, column: Any, source: Any, n: int, kept: Any = None, key: str = "validation.weights"
) -> Any:
    """Validation weights (Eq. 22) from a column of a CSV file.

    With ``kept`` (a mask over the file's rows) the weights of those rows only; the
    others' cells may be empty, and a bad value is named by its row in the file.
    """
    try:
        if not isinstance(column, str):
            raise ValueError(f"must be a column name, got {column!r}")
        frame = read_csv_table(source)
        if column not in frame:
            raise ValueError(f"column {column!r} not in {source}")
        values = frame[column].to_numpy()
        if kept is None:
            return check_validation_weights(values, n)
        weights = check_validation_weights(np.where(kept, values, 0.0), len(values))[kept]
        return check_validation_weights(weights, n)
    except ValueError as err:
        raise _err(path, key, f"{err} ({source})") from err


def _emulator_section(
    path: Path,
    doc: dict,
    formulations: Mapping[str, Any],
    inputs: Sequence[str] | None = None,
) -> Any:
    """``[emulator]``: :class:`kohpymc.emulator.study.EmulatorSettings`, or None.

    ``inputs`` (the physics inputs) must contain the ``functional`` ones; without
    ``inputs`` (several outputs) ``functional`` is an error.
    """
    from kohpymc.emulator.study import EmulatorSettings

    if "emulator" not in doc:
        return None
    try:
        settings = EmulatorSettings.from_table(doc["emulator"])
    except KeyError as err:
        why = "; ".join(getattr(err, "__notes__", [])) or "invalid"
        raise _err(path, f"emulator.{err.args[0]}", why) from err
    label = settings.formulation
    if label is not None and label not in formulations:
        raise _err(
            path,
            "emulator.formulation",
            f"{label!r} is not one of the formulations {list(formulations)}",
        )
    if settings.functional:
        _check_functional(path, settings.functional, inputs)
    return settings


def _check_functional(path: Path, names: Sequence[str], inputs: Sequence[str] | None) -> None:
    """``[emulator] functional`` names physics inputs (a single-output study only)."""
    if inputs is None:
        raise _err(
            path,
            "emulator.functional",
            f"is {list(names)}, but a functional emulator is for single-output studies",
        )
    unknown = [k for k in names if k not in inputs]
    if unknown:
        raise _err(
            path,
            "emulator.functional",
            f"{unknown} are not inputs of the physics (inputs: {list(inputs)})",
        )


def _read_document(path: Path) -> dict:
    """The parsed TOML file with its sections and their keys checked."""
    if not path.is_file():
        raise StudyConfigError(f"study file {path} not found")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as err:
        raise StudyConfigError(
            f"{path}: not UTF-8 text (byte {err.object[err.start]:#04x} at offset {err.start})"
        ) from err
    except OSError as err:
        raise StudyConfigError(f"{path}: cannot be read: {err.strerror or err}") from err
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise StudyConfigError(f"{path}: not valid TOML: {err}") from err
    _check_keys(path, "top level", doc, set(_SECTIONS))
    for section, allowed in _SECTIONS.items():
        if section in doc:
            if not isinstance(doc[section], dict):
                raise _err(path, section, "must be a table")
            if allowed is not None:
                _check_keys(path, section, doc[section], allowed)
    for section in ("physics", "data", "validation"):
        if section not in doc:
            raise _err(path, section, "section is required but missing")
    name = doc.get("study", {}).get("name")
    if name is not None and not isinstance(name, str):
        raise _err(path, "study.name", f"must be text, got {name!r}")
    return doc


def _physics_section(path: Path, base: Path, phys: dict):
    """``[physics]``: the model, its inputs, output column and time input."""
    function = _load_callable(
        _require(path, phys, "physics", "function"), base, path, "physics.function"
    )
    inputs = _names(path, "physics.inputs", _require(path, phys, "physics", "inputs"))
    if not inputs:
        raise _err(path, "physics.inputs", "must name at least one input column")
    output = _require(path, phys, "physics", "output")
    if isinstance(output, list):
        raise _err(
            path, "physics.output", f"is a list of outputs {output}: read a multi-output study "
            "with kohpymc.load_multi_output_study (docs/multi-output.md)",
        )  # fmt: skip
    if not isinstance(output, str) or not output:
        raise _err(path, "physics.output", f"must be a column name, got {output!r}")
    if output in inputs:
        raise _err(path, "physics.output", f"{output!r} is also one of the inputs {inputs}")
    priors = _priors(path, _require(path, phys, "physics", "parameters"), inputs)
    jacobian = (
        _load_callable(phys["jacobian"], base, path, "physics.jacobian")
        if "jacobian" in phys
        else None
    )
    time = _time_input(path, phys, inputs)
    if not isinstance(phys.get("name", ""), str):
        raise _err(path, "physics.name", f"must be text, got {phys['name']!r}")
    kwargs = {k: phys[k] for k in PHYSICS_OPTIONS if k in phys}
    try:
        physics = PhysicsModel(function, priors, inputs, jacobian=jacobian, **kwargs)
    except (TypeError, ValueError, KeyError) as err:
        where = next((f"physics.{k}" for k in PHYSICS_OPTIONS if k in str(err)), None)
        raise _err(path, where or "physics", str(err)) from err
    return physics, inputs, output, time


def _time_input(path: Path, phys: dict, inputs: list[str]) -> str | None:
    """``[physics] time``: the input M5's variance drifts along, or None."""
    time = phys.get("time")
    if time is not None and (not isinstance(time, str) or time not in inputs):
        raise _err(path, "physics.time", f"{time!r} is not one of the inputs {inputs}")
    return time


def _priors(path: Path, params: Any, inputs: list[str]) -> dict[str, Any]:
    """``[physics.parameters]``: one prior per parameter (each checked, its key named)."""
    if not isinstance(params, dict) or not params:
        raise _err(path, "physics.parameters", "must be a table of parameter priors")
    priors = {}
    for name, value in params.items():
        key = f"physics.parameters.{name}"
        if name in inputs:
            raise _err(path, key, f"{name!r} is also one of the inputs {inputs}")
        if not isinstance(value, dict):
            raise _err(path, key, f"must be a prior table like {{ prior = ... }}, got {value!r}")
        try:
            priors[name] = as_prior(value, name=name)
        except (TypeError, ValueError) as err:
            raise _err(path, key, str(err)) from err
    return priors


#: what a loader of one data file returns
T = TypeVar("T")


def _validation_data(
    load: Callable[[Any, Any], T], noise_sd: Any, replicates: Any, pooled: Any
) -> T:
    """``[data] validation`` by ``load(noise_sd, replicates)``; without repeats, ``pooled``.

    The validation rows come from the same instrument: when ``replicates`` is set and no
    validation setting was measured twice, the calibration data's pooled σ (``pooled``:
    one number, or per output for a multi-output study) stands for theirs instead of
    failing.
    """
    try:
        return load(noise_sd, replicates)
    except StudyConfigError as err:
        if not isinstance(err.__cause__, NoReplicatesError) or pooled is None:
            raise
    return load(pooled, None)


def _data_section(path: Path, base: Path, data: dict, physics, inputs, output):
    """``[data]``: the calibration and validation data (the model must run on the latter)."""
    noise_sd = data.get("noise_sd")
    if noise_sd is not None:
        try:
            noise_sd = check_positive_number(noise_sd, "noise_sd")
        except ValueError as err:
            raise _err(path, "data.noise_sd", str(err).removeprefix("noise_sd ")) from err
    replicates = _replicates(path, "data.replicates", data.get("replicates"))
    calibration = _data(
        path, base, "data.calibration", _require(path, data, "data", "calibration"),
        inputs, output, noise_sd, replicates,
    )  # fmt: skip
    file = _require(path, data, "data", "validation")
    validation = _validation_data(
        lambda noise, groups: _data(
            path, base, "data.validation", file, inputs, output, noise, groups
        ),
        noise_sd, replicates, calibration.noise_sd,
    )  # fmt: skip
    if validation.n == 0:
        raise _err(path, "data.validation", f"{validation.source} has no rows")
    if calibration.n < len(physics.parameters):
        raise _err(
            path, "data.calibration",
            f"{calibration.source} has {calibration.n} row(s) for {len(physics.parameters)} "
            f"physics parameters {list(physics.parameters)}: the identifiability check of "
            "every formulation needs at least one row per parameter",
        )  # fmt: skip
    for key, data_set in (("calibration", calibration), ("validation", validation)):
        try:
            check_physics_runs(physics, data_set, key)
        except JacobianError as err:
            raise _err(path, "physics.jacobian", str(err)) from err
        except (KeyError, ValueError) as err:
            raise _err(path, f"data.{key}", str(err).strip("'\"")) from err
    return calibration, validation


def _units_table(path: Path, table: Any, inputs, output) -> dict[str, str] | None:
    """``[data.units]``: input (and output) name -> unit string, each one parsed."""
    from kohpymc.units import UnitError, parse_unit

    if table is None:
        return None
    if not isinstance(table, dict):
        raise _err(path, "data.units", 'must be a table, e.g. [data.units] t = "s"')
    out: dict[str, str] = {}
    for key, text in table.items():
        name = "output" if key in ("output", output) else key
        if name != "output" and key not in inputs:
            raise _err(path, f"data.units.{key}", f"not an input {list(inputs)} nor the output")
        try:
            parse_unit(text)
        except UnitError as err:
            raise _err(path, f"data.units.{key}", str(err)) from err
        out[name] = text
    return out


def _validation_section(path: Path, val: dict, validation):
    """``[validation]``: the tolerance and the optional weight column."""
    try:
        tolerance = check_tolerance(_require(path, val, "validation", "tolerance"))
    except ValueError as err:
        raise _err(path, "validation.tolerance", str(err)) from err
    weights = None
    if "weights" in val:
        weights = _weight_column(path, val["weights"], validation.source, validation.n)
    return tolerance, weights


def _formulations_section(path: Path, doc: dict, inputs, time):
    """``[formulations]``, or the default set when absent or empty."""
    if "formulations" in doc and doc["formulations"]:
        return {
            str(label): _formulation(path, str(label), value, inputs, time)
            for label, value in doc["formulations"].items()
        }
    return default_formulations(inputs, time=time)


def _sampling_section(path: Path, doc: dict) -> dict:
    """``[sampling]``: sampler settings (``seed`` read as ``random_seed``)."""
    sampling_doc = dict(doc.get("sampling", {}))
    if "seed" in sampling_doc:
        sampling_doc["random_seed"] = sampling_doc.pop("seed")
    for key in ("draws", "tune", "chains", "cores"):
        if key in sampling_doc:
            value = sampling_doc[key]
            try:
                check_count(value, key)
            except ValueError as err:
                message = f"must be a positive integer, got {value!r}"
                raise _err(path, f"sampling.{key}", message) from err
    if "random_seed" in sampling_doc:
        _count(path, "sampling.seed", sampling_doc["random_seed"], minimum=0)
    if "target_accept" in sampling_doc:
        try:
            check_target_accept(sampling_doc["target_accept"])
        except ValueError as err:
            raise _err(path, "sampling.target_accept", str(err)) from err
    try:
        check_compile_mode(sampling_doc.get("mode"))
    except ValueError as err:
        raise _err(path, "sampling.mode", str(err)) from err
    for key in ("sampler", "method"):
        if key in sampling_doc:
            try:
                check_sampler(sampling_doc[key], key)
            except ValueError as err:
                raise _err(path, f"sampling.{key}", str(err)) from err
    try:
        resolve_sampler(sampling_doc.get("sampler"), sampling_doc.get("method"))
    except ValueError as err:
        raise _err(path, "sampling", str(err)) from err
    if not isinstance(sampling_doc.get("reparameterize", True), bool):
        raise _err(path, "sampling.reparameterize", "must be true or false")
    return sampling_doc


def _execution_section(path: Path, doc: dict, old_workers: Any) -> dict[str, Any]:
    """``[execution]``: ``workers`` (alias: the older ``[sampling] workers``), ``scheduler``."""
    table = dict(doc.get("execution", {}))
    if old_workers is not None:
        try:
            check_workers(old_workers)
        except ValueError as err:
            raise _err(path, "sampling.workers", str(err)) from err
        if "workers" in table and table["workers"] != old_workers:
            raise _err(
                path, "execution.workers",
                f"{table['workers']!r} differs from [sampling] workers = {old_workers!r} "
                "(its older spelling); give one",
            )  # fmt: skip
        table.setdefault("workers", old_workers)
    if "workers" in table:
        try:
            check_workers(table["workers"])
        except ValueError as err:
            raise _err(path, "execution.workers", str(err)) from err
    if "scheduler" in table:
        try:
            check_scheduler(table["scheduler"])
        except ValueError as err:
            raise _err(path, "execution.scheduler", str(err)) from err
        if table.get("workers", 1) > 1:
            raise _err(
                path, "execution", "give workers (a local cluster) or scheduler (an existing "
                "cluster), not both",
            )  # fmt: skip
    return table


def _count(path: Path, key: str, value: Any, minimum: int = 1) -> int:
    try:
        return check_count(value, key, minimum=minimum)
    except ValueError as err:
        raise _err(path, key, str(err).removeprefix(f"{key} ")) from err


def _check_section(path: Path, table: dict, physics: PhysicsModel, formulations) -> CheckSpec:
    """``[check]``: settings of ``kohpymc check`` and an optional simulation override."""
    spec = CheckSpec()
    label = table.get("formulation")
    if label is not None and (not isinstance(label, str) or label not in formulations):
        raise _err(
            path,
            "check.formulation",
            f"{label!r} is not one of the formulations {list(formulations)}",
        )
    spec.formulation = label
    for key in ("replicates", "draws", "tune", "chains", "rank_draws"):
        if key in table:
            setattr(spec, key, _count(path, f"check.{key}", table[key]))
    if "seed" in table:
        spec.seed = _count(path, "check.seed", table["seed"], minimum=0)
    simulate = table.get("simulate", {})
    if not isinstance(simulate, dict):
        raise _err(path, "check.simulate", "must be a table")
    _check_keys(path, "check.simulate", simulate, _SIMULATE_KEYS)
    _simulate_section(path, simulate, physics, spec)
    return spec


def _simulate_section(path: Path, simulate: dict, physics: PhysicsModel, spec: CheckSpec) -> None:
    """``[check.simulate]``: priors of the true parameters and the simulation's noise."""
    params = simulate.get("parameters", {})
    if not isinstance(params, dict):
        raise _err(path, "check.simulate.parameters", "must be a table of parameter priors")
    for name, value in params.items():
        key = f"check.simulate.parameters.{name}"
        if name not in physics.parameters:
            raise _err(path, key, f"is not a physics parameter {list(physics.parameters)}")
        try:
            spec.simulate_parameters[name] = as_prior(value, name=name)
        except (TypeError, ValueError) as err:
            raise _err(path, key, str(err)) from err
    if "noise_sd" in simulate and "sigma_obs" in simulate:
        raise _err(path, "check.simulate", "give noise_sd (fixed) or sigma_obs (a prior), not both")
    if "noise_sd" in simulate:
        value = simulate["noise_sd"]
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        if not ok or not math.isfinite(value) or value <= 0:
            raise _err(path, "check.simulate.noise_sd", f"must be a positive number, got {value!r}")
        spec.simulate_noise_sd = float(value)
    if "sigma_obs" in simulate:
        try:
            spec.simulate_noise_prior = as_prior(simulate["sigma_obs"], name="sigma_obs")
        except (TypeError, ValueError) as err:
            raise _err(path, "check.simulate.sigma_obs", str(err)) from err
