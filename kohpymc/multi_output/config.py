"""Multi-output studies from TOML: ``[physics] output = ["u", "strain"]``.

The file has the keys of a single-output study (:mod:`kohpymc.config`) with these
differences::

    [physics]
    function = "kohpymc.examples.beam_multi_output:beam_outputs"   # returns {output: array}
    jacobian = "kohpymc.examples.beam_multi_output:beam_outputs_jacobian"  # optional
    inputs = ["x", "P"]
    output = ["u", "strain"]            # a list: the outputs' columns of the CSV files
    # time = "P"                        # optional: M5 joins the default formulations
    [physics.parameters]
    E = { prior = "uniform", lower = 50, upper = 300 }

    [data]
    calibration = "cal.csv"             # one column per input and per output
    validation = "val.csv"
    noise_sd = { u = 0.316, strain = 3.0 }    # per output (or one number for all);
                                              # outputs left out are calibrated

    # replicates = "inputs"             # or a column, or per output { u = "inputs" }
    # [data.units]                      # optional (discover): inputs' and outputs' units
    # x = "mm"
    # u = "um"
    [validation]
    tolerance = { u = 0.75, strain = 7.5 }    # per output, in its units
    # weights = "w"                     # a column of the validation CSV (Eq. 22), read at
                                        # each output's rows; or per output { u = "w_u" }

    [formulations]                      # label -> discrepancy of every output; default
                                        # M0–M4 of a single-output study, each for all outputs
    M0 = "none"                         # one type for all outputs
    M31 = { u = { type = "input_dependent", mean = ["x", "P", "x*P"] }, strain = "constant" }
    ICM = { type = "coregionalized", inputs = ["x"], rank = 1 }   # joint multi-output GP
    # kernel = "Matern52" (or "Matern32", "Exponential"; default "ExpQuad") in that table

    [emulator]                          # optional: an expensive simulator emulated, one
    runs = 200                          # design, every run gives all outputs, one GP per
    # design = "maximin-lhs"            # output (kohpymc.multi_output.emulator); keys as
                                        # for one output except sequential (must be 0), and
                                        # no coregionalized formulation beside it;
                                        # refine_at_data rounds check all outputs jointly

    [execution]                         # as for one output: formulations as Dask tasks
    workers = 2                         # (or scheduler = "tcp://HOST:PORT")
    [output]
    dir = "beam_multi_output"           # the CLI's --out wins

Every problem names the file and the key (``[data.noise_sd.strian]``), or the file and
the column of a CSV file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.checks import check_positive_number, check_tolerance
from kohpymc.config import (
    PHYSICS_OPTIONS,
    _emulator_section,
    _err,
    _execution_section,
    _formulation,
    _load_callable,
    _names,
    _output_dir,
    _priors,
    _read_document,
    _replicates,
    _require,
    _sampling_section,
    _time_input,
    _units_table,
    _validation_data,
    _weight_column,
)
from kohpymc.data import read_csv_table
from kohpymc.discrepancy.defaults import default_formulations
from kohpymc.multi_output.coregionalized import Coregionalized
from kohpymc.multi_output.data import MultiOutputData
from kohpymc.multi_output.physics import MultiOutputPhysics

__all__ = ["MultiOutputStudySpec", "load_multi_output_study"]


@dataclass
class MultiOutputStudySpec:
    """A checked multi-output study file.

    Attributes
    ----------
    source : Path
    physics : MultiOutputPhysics
    calibration, validation : MultiOutputData
    tolerance : dict of str to float
        ε per output.
    formulations : dict
        Label -> a formulation, a mapping output -> formulation, or a
        :class:`~kohpymc.multi_output.Coregionalized`.
    sampling : dict
        Keywords for :func:`~kohpymc.multi_output.calibrate_outputs`.
    validation_weights : dict of str to array, or None
        ``w_i`` of Eq. 22 per output (outputs left out: uniform).
    execution : dict
        ``workers`` and/or ``scheduler`` (``[execution]``).
    out_dir : Path
        ``[output] dir`` relative to the file, default ``<file stem>_results`` beside it.
    units : dict or None
        ``[data.units]`` per output: output -> {input: unit, "output": unit}, read by
        ``kohpymc discover`` (:func:`~kohpymc.multi_output.discover_outputs`).
    emulator : EmulatorSettings or None
        The ``[emulator]`` table: calibrate through one GP emulator per output
        (:func:`~kohpymc.multi_output.emulator.study_outputs_physics`).
    """

    source: Path
    physics: MultiOutputPhysics
    calibration: MultiOutputData
    validation: MultiOutputData
    tolerance: dict[str, float]
    formulations: dict[str, Any]
    sampling: dict[str, Any] = field(default_factory=dict)
    validation_weights: dict[str, np.ndarray] | None = None
    execution: dict[str, Any] = field(default_factory=dict)
    out_dir: Path = Path("study_results")
    units: dict[str, dict[str, str]] | None = None
    emulator: Any = None


def _outputs(path: Path, value: Any, inputs: list[str]) -> list[str]:
    if isinstance(value, str):
        value = [value]
    outputs = _names(path, "physics.output", value)
    clash = [k for k in outputs if k in inputs]
    if clash:
        raise _err(path, "physics.output", f"{clash} are also inputs {inputs}")
    bad = [k for k in outputs if not k.isidentifier()]
    if bad:
        raise _err(path, "physics.output", f"output names must be identifiers, got {bad}")
    return outputs


def _per_output_table(path: Path, key: str, value: Any, outputs: list[str], check) -> dict:
    """One number for all outputs, or a table output -> number (keys checked)."""
    if not isinstance(value, dict):
        value = dict.fromkeys(outputs, value)
    unknown = [k for k in value if k not in outputs]
    if unknown:
        raise _err(path, f"{key}.{unknown[0]}", f"is not an output; outputs are {outputs}")
    out = {}
    for name, number in value.items():
        try:
            out[name] = check(number)
        except (TypeError, ValueError) as err:
            raise _err(path, f"{key}.{name}", str(err)) from err
    return out


def _multi_data(path: Path, base: Path, key: str, file: Any, inputs, outputs, noise, groups):
    if not isinstance(file, str):
        raise _err(path, key, f"must be a CSV file name, got {file!r}")
    csv = (base / file).resolve()
    if not csv.is_file():
        raise _err(path, key, f"data file {csv} not found")
    try:
        return MultiOutputData.from_csv(
            csv, inputs=inputs, outputs=outputs, noise_sd=noise, replicates=groups
        )
    except (KeyError, ValueError, TypeError) as err:
        raise _err(path, key, str(err).strip("'\"")) from err


def _per_output_replicates(path: Path, value: Any, outputs: list[str]) -> Any:
    """``[data] replicates``: one value for every output, or a table output -> value."""
    if not isinstance(value, dict):
        return _replicates(path, "data.replicates", value)
    unknown = [k for k in value if k not in outputs]
    if unknown:
        raise _err(
            path, f"data.replicates.{unknown[0]}", f"is not an output; outputs are {outputs}"
        )
    return {k: _replicates(path, f"data.replicates.{k}", v) for k, v in value.items()}


def _per_output_units(path: Path, table: Any, inputs: list[str], outputs: list[str]) -> Any:
    """``[data.units]``: inputs' and outputs' units, as one single-output table per output."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise _err(path, "data.units", 'must be a table, e.g. [data.units] x = "mm"')
    unknown = [k for k in table if k not in inputs and k not in outputs]
    if unknown:
        raise _err(
            path, f"data.units.{unknown[0]}", f"is not an input {inputs} nor an output {outputs}"
        )
    shared = {k: v for k, v in table.items() if k in inputs}
    return {
        k: _units_table(path, {**shared, **({k: table[k]} if k in table else {})}, inputs, k)
        for k in outputs
    }


def _validation_weights(path: Path, value: Any, validation: MultiOutputData) -> dict:
    """``[validation] weights``: a column for all outputs, or a table output -> column.

    Each output's weights are the column at the rows that output keeps (a row whose
    output cell is empty belongs to the other outputs only).
    """
    columns = value if isinstance(value, dict) else dict.fromkeys(validation.outputs, value)
    unknown = [k for k in columns if k not in validation.outputs]
    if unknown:
        raise _err(
            path, f"validation.weights.{unknown[0]}",
            f"is not an output; outputs are {list(validation.outputs)}",
        )  # fmt: skip
    weights = {}
    for name, column in columns.items():
        source = validation[name].source
        frame = read_csv_table(str(source))  # read by from_csv: source is the file
        kept = pd.to_numeric(frame[name], errors="coerce").notna().to_numpy()
        key = "validation.weights" + ("" if not isinstance(value, dict) else f".{name}")
        weights[name] = _weight_column(path, column, source, validation[name].n, kept, key)
    return weights


def _multi_formulation(path: Path, label: str, value: Any, inputs, outputs, time) -> Any:
    key = f"formulations.{label}"
    if isinstance(value, dict) and value.get("type") == "coregionalized":
        options = {k: v for k, v in value.items() if k != "type"}
        unknown = sorted(set(options) - {"inputs", "rank", "kernel"})
        if unknown:
            raise _err(path, key, f"coregionalized: unknown option(s) {unknown}")
        gp_inputs = _names(path, f"{key}.inputs", options.get("inputs", inputs))
        absent = [k for k in gp_inputs if k not in inputs]
        if absent:
            raise _err(path, f"{key}.inputs", f"{absent} are not physics inputs {inputs}")
        try:
            return Coregionalized(
                gp_inputs, rank=options.get("rank", 1), kernel=options.get("kernel", "ExpQuad")
            )
        except ValueError as err:
            bad = "kernel" if "kernel" in str(err) else "rank"
            raise _err(path, f"{key}.{bad}", str(err)) from err
    if isinstance(value, dict) and "type" not in value:
        unknown = [k for k in value if k not in outputs]
        if unknown:
            raise _err(path, f"{key}.{unknown[0]}", f"is not an output; outputs are {outputs}")
        return {k: _formulation(path, f"{label}.{k}", v, inputs, time) for k, v in value.items()}
    return _formulation(path, label, value, inputs, time)


#: keys of a single-output study file that a multi-output study does not run (each was
#: read and silently ignored: an [emulator] section left the slow simulator called directly)
_SINGLE_OUTPUT_ONLY = (("check", None, "run `kohpymc check`"),)


def _unsupported(path: Path, doc: dict) -> None:
    """Stop at a section or key that only single-output studies act on, naming it."""
    for section, key, what in _SINGLE_OUTPUT_ONLY:
        table = doc.get(section)
        if table is None or (key is not None and key not in table):
            continue
        name = section if key is None else f"{section}.{key}"
        raise _err(path, name, f"a multi-output study cannot {what} yet; remove it")


def load_multi_output_study(path: str | Path) -> MultiOutputStudySpec:
    """Read and check a multi-output study file (keys: see the module docstring).

    Raises
    ------
    StudyConfigError
        Naming the file and the key, e.g. a ``noise_sd`` key that is not an output or
        an output column missing from a CSV file.

    Examples
    --------
    >>> from importlib.resources import files
    >>> spec = load_multi_output_study(
    ...     files("kohpymc.examples") / "beam_multi_output_study.toml")
    >>> spec.calibration.outputs, spec.tolerance
    (('u', 'strain'), {'u': 0.75, 'strain': 7.5})
    """
    path = Path(path)
    doc = _read_document(path)
    _unsupported(path, doc)
    base = path.resolve().parent
    phys = doc["physics"]
    function = _load_callable(
        _require(path, phys, "physics", "function"), base, path, "physics.function"
    )
    inputs = _names(path, "physics.inputs", _require(path, phys, "physics", "inputs"))
    outputs = _outputs(path, _require(path, phys, "physics", "output"), inputs)
    priors = _priors(path, _require(path, phys, "physics", "parameters"), inputs)
    time = _time_input(path, phys, inputs)
    jacobian = (
        _load_callable(phys["jacobian"], base, path, "physics.jacobian")
        if "jacobian" in phys
        else None
    )
    kwargs = {k: phys[k] for k in PHYSICS_OPTIONS if k in phys}
    try:
        physics = MultiOutputPhysics(function, priors, inputs, outputs, jacobian=jacobian, **kwargs)
    except (TypeError, ValueError, KeyError) as err:
        raise _err(path, "physics", str(err)) from err
    data = doc["data"]
    noise = None
    if data.get("noise_sd") is not None:
        noise = _per_output_table(
            path, "data.noise_sd", data["noise_sd"], outputs,
            lambda v: check_positive_number(v, "noise_sd"),
        )  # fmt: skip
    groups = _per_output_replicates(path, data.get("replicates"), outputs)
    calibration = _multi_data(
        path, base, "data.calibration", _require(path, data, "data", "calibration"),
        inputs, outputs, noise, groups,
    )  # fmt: skip
    file = _require(path, data, "data", "validation")
    pooled = {k: calibration[k].noise_sd for k in outputs if calibration[k].noise_sd is not None}
    validation = _validation_data(
        lambda noise_sd, replicates: _multi_data(
            path, base, "data.validation", file, inputs, outputs, noise_sd, replicates
        ),
        noise, groups, {**pooled, **(noise or {})},
    )  # fmt: skip
    for key, data_set in (("calibration", calibration), ("validation", validation)):
        for name in outputs:
            try:
                physics.output(name).regular_point(data_set[name].inputs)
            except Exception as err:  # noqa: BLE001 - any failure is reported with its key
                raise _err(path, f"data.{key}", f"output {name!r}: {err}") from err
    val = doc["validation"]
    tolerance = _per_output_table(
        path, "validation.tolerance", _require(path, val, "validation", "tolerance"), outputs,
        check_tolerance,
    )  # fmt: skip
    missing = [k for k in outputs if k not in tolerance]
    if missing:
        raise _err(path, "validation.tolerance", f"gives no value for output(s) {missing}")
    weights = _validation_weights(path, val["weights"], validation) if "weights" in val else None
    table = doc.get("formulations")
    formulations = (
        {
            str(label): _multi_formulation(path, str(label), value, inputs, outputs, time)
            for label, value in table.items()
        }
        if table
        else dict(default_formulations(inputs, time=time))  # as for one output: M0–M4 (M5)
    )
    sampling = _sampling_section(path, doc)
    execution = _execution_section(path, doc, sampling.pop("workers", None))
    return MultiOutputStudySpec(
        path, physics, calibration, validation, tolerance, formulations, sampling,
        weights, execution, _output_dir(path, base, doc),
        _per_output_units(path, data.get("units"), inputs, outputs),
        _multi_emulator_section(path, doc, formulations),
    )  # fmt: skip


def _multi_emulator_section(path: Path, doc: dict, formulations: dict[str, Any]) -> Any:
    """``[emulator]`` as for one output, without sequential rounds or a joint GP beside it."""
    settings = _emulator_section(path, doc, formulations)
    if settings is None:
        return None
    if settings.sequential > 0:
        raise _err(
            path, "emulator.sequential",
            f"is {settings.sequential}: sequential design rounds are for single-output "
            "studies; a multi-output emulator takes its runs from one design (sequential = 0, "
            "more runs = N instead)",
        )  # fmt: skip
    for label, formulation in formulations.items():
        if isinstance(formulation, Coregionalized):
            raise _err(
                path, f"formulations.{label}",
                "a coregionalized formulation does not carry the emulators' variance into "
                "its joint likelihood; with [emulator] use per-output formulations",
            )  # fmt: skip
    return settings
