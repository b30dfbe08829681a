"""Data with several output columns: one :class:`~kohpymc.CalibrationData` per output.

The outputs are kept in long form: output ``k`` has its own rows (its own inputs, which
may be the rows of a shared table or a table of its own), its own observed values and
its own measurement-noise sd σ_obs,k (known, pooled from replicates, or calibrated).
Stacking the outputs' rows, output by output in the order of :attr:`MultiOutputData.outputs`,
gives the long-form vector the joint likelihood is written over.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from os import PathLike
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData, non_numeric_entry, read_csv_table

__all__ = ["MultiOutputData", "per_output"]


def per_output(value: Any, outputs: Sequence[str], what: str, source: str | None = None) -> dict:
    """Spread a setting over the outputs: one value for all, or a mapping output -> value.

    A mapping must name outputs only; outputs it leaves out get ``None``.

    Examples
    --------
    >>> per_output(0.3, ["u", "strain"], "noise_sd")
    {'u': 0.3, 'strain': 0.3}
    >>> per_output({"u": 0.3}, ["u", "strain"], "noise_sd")
    {'u': 0.3, 'strain': None}
    >>> per_output({"w": 0.3}, ["u", "strain"], "noise_sd")
    Traceback (most recent call last):
    ...
    KeyError: "noise_sd names 'w', which is not an output; outputs are ['u', 'strain']"
    """
    if not isinstance(value, Mapping):
        return {name: value for name in outputs}
    where = f" in {source}" if source else ""
    unknown = [k for k in value if k not in outputs]
    if unknown:
        raise KeyError(
            f"{what}{where} names {unknown[0]!r}, which is not an output; "
            f"outputs are {list(outputs)}"
        )
    return {name: value.get(name) for name in outputs}


class MultiOutputData:
    """Measured data with several outputs that calibrate one θ jointly.

    Parameters
    ----------
    data : mapping of str to CalibrationData
        One data set per output (its ``output_name`` is replaced by the key).  Every
        output needs the same input columns.

    Examples
    --------
    >>> import pandas as pd
    >>> frame = pd.DataFrame({"x": [1.0, 2.0, 3.0], "u": [0.1, 0.2, 0.3],
    ...                       "strain": [3e-5, 2e-5, None]})
    >>> data = MultiOutputData.from_dataframe(frame, inputs=["x"], outputs=["u", "strain"],
    ...                                       noise_sd={"u": 0.01, "strain": 1e-6})
    >>> data.outputs, data.sizes
    (('u', 'strain'), {'u': 3, 'strain': 2})
    >>> data["strain"].noise_sd
    1e-06
    """

    def __init__(self, data: Mapping[str, CalibrationData]) -> None:
        if not isinstance(data, Mapping) or not data:
            raise ValueError("multi-output data need a mapping output name -> CalibrationData")
        out: dict[str, CalibrationData] = {}
        for name, part in data.items():
            if not isinstance(part, CalibrationData):
                raise TypeError(
                    f"output {name!r}: expected CalibrationData, got {type(part).__name__}"
                )
            part = part.subset(np.arange(part.n))
            part.output_name = str(name)
            out[str(name)] = part
        first = next(iter(out.values()))
        for name, part in out.items():
            if set(part.input_names) != set(first.input_names):
                raise ValueError(
                    f"output {name!r} has inputs {list(part.input_names)} but output "
                    f"{first.output_name!r} has {list(first.input_names)}"
                )
        self.data: dict[str, CalibrationData] = out

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_dataframe(
        cls,
        frame: pd.DataFrame,
        *,
        inputs: Sequence[str],
        outputs: Sequence[str],
        noise_sd: float | Mapping[str, float | None] | None = None,
        replicates: str | Mapping[str, str | None] | None = None,
        source: str | None = None,
    ) -> MultiOutputData:
        """One table, one column per input and per output.

        An output's missing values (empty cells, NaN) drop that row for that output
        only.  ``noise_sd`` is one value for all outputs or a table output -> value
        (outputs left out are calibrated, or pooled from replicates).  ``replicates``
        (``"inputs"`` or a column of group labels, for all outputs or per output) marks
        an output's rows that repeat one setting, as for one output
        (:class:`~kohpymc.CalibrationData`): without a known noise sd, the output's σ_obs
        is their pooled sd (paper Eq. 28), from the rows that output keeps.

        Raises
        ------
        KeyError
            Naming the missing column (and the file) or the ``noise_sd`` key that is
            not an output.
        """
        where = f" in {source}" if source else ""
        outputs = _output_names(outputs)
        clash = [k for k in outputs if k in inputs]
        if clash:
            raise ValueError(f"output(s) {clash} are also inputs {list(inputs)}")
        missing = [c for c in [*inputs, *outputs] if c not in frame.columns]
        if missing:
            kind = "output" if all(c in outputs for c in missing) else "input/output"
            raise KeyError(
                f"{kind} column(s) {missing} not found{where}; columns: {list(frame.columns)}"
            )
        noise = per_output(noise_sd, outputs, "noise_sd", source)
        groups = per_output(replicates, outputs, "replicates", source)
        parts = {}
        for name in outputs:
            column = pd.to_numeric(frame[name], errors="coerce")
            bad = frame[name].notna() & column.isna()
            if bad.any():
                raise TypeError(
                    f"output column {name!r}{where} has a non-numeric value "
                    f"{non_numeric_entry(frame[name])}"
                )
            keep = column.notna().to_numpy()
            if not keep.any():
                raise ValueError(f"output column {name!r}{where} has no values")
            sub = frame.loc[keep].assign(**{name: column[keep]})
            parts[name] = CalibrationData.from_dataframe(
                sub,
                inputs=inputs,
                output=name,
                noise_sd=noise[name],
                replicates=groups[name],
                source=source,
            )
        return cls(parts)

    @classmethod
    def from_csv(
        cls,
        path: str | PathLike[str],
        *,
        inputs: Sequence[str],
        outputs: Sequence[str],
        noise_sd: float | Mapping[str, float | None] | None = None,
        replicates: str | Mapping[str, str | None] | None = None,
    ) -> MultiOutputData:
        r"""Read one CSV file with a column per input and per output.

        Examples
        --------
        >>> import os, tempfile
        >>> path = os.path.join(tempfile.mkdtemp(), "d.csv")
        >>> _ = open(path, "w").write("x,u\n1,2\n")
        >>> MultiOutputData.from_csv(path, inputs=["x"], outputs=["u", "strain"])
        Traceback (most recent call last):
        ...
        KeyError: "output column(s) ['strain'] not found in .../d.csv; columns: ['x', 'u']"
        """
        return cls.from_dataframe(
            read_csv_table(path),
            inputs=inputs,
            outputs=outputs,
            noise_sd=noise_sd,
            replicates=replicates,
            source=str(path),
        )

    # --------------------------------------------------------------------- accessors
    @property
    def outputs(self) -> tuple[str, ...]:
        """Output names, in stacking order."""
        return tuple(self.data)

    @property
    def sizes(self) -> dict[str, int]:
        """Rows per output."""
        return {k: v.n for k, v in self.data.items()}

    @property
    def n(self) -> int:
        """Rows of all outputs together (the length of the stacked vector)."""
        return sum(self.sizes.values())

    @property
    def input_names(self) -> tuple[str, ...]:
        """Input columns (shared by every output)."""
        return next(iter(self.data.values())).input_names

    @property
    def noise_sd(self) -> dict[str, float | None]:
        """σ_obs per output (``None``: calibrated)."""
        return {k: v.noise_sd for k, v in self.data.items()}

    def __getitem__(self, name: str) -> CalibrationData:
        try:
            return self.data[name]
        except KeyError:
            raise KeyError(f"no output {name!r}; outputs are {list(self.outputs)}") from None

    def __iter__(self):
        return iter(self.data)

    def __len__(self) -> int:
        return len(self.data)

    def stacked(self) -> pd.DataFrame:
        """Long form: one row per (output, measurement), columns inputs, ``output``, ``y``.

        Examples
        --------
        >>> from kohpymc import CalibrationData
        >>> d = MultiOutputData({"a": CalibrationData({"x": [1.0]}, [2.0]),
        ...                      "b": CalibrationData({"x": [1.0, 2.0]}, [3.0, 4.0])})
        >>> d.stacked()["output"].tolist()
        ['a', 'b', 'b']
        """
        frames = []
        for name, part in self.data.items():
            frame = pd.DataFrame(part.inputs)
            frame["output"] = name
            frame["y"] = part.y
            frames.append(frame)
        return pd.concat(frames, ignore_index=True)

    def select(self, outputs: Sequence[str]) -> MultiOutputData:
        """The named outputs only (e.g. to calibrate on one output alone).

        Examples
        --------
        >>> from kohpymc import CalibrationData
        >>> d = MultiOutputData({"a": CalibrationData({"x": [1.0]}, [2.0]),
        ...                      "b": CalibrationData({"x": [1.0]}, [3.0])})
        >>> d.select(["b"]).outputs
        ('b',)
        """
        outputs = _output_names(outputs)
        return MultiOutputData({k: self[k] for k in outputs})

    # ------------------------------------------------------------------------ splits
    def split(
        self, rule: Callable[[CalibrationData], Any]
    ) -> tuple[MultiOutputData, MultiOutputData]:
        """``(rows where rule(output data) is True, the rest)``, output by output.

        Examples
        --------
        >>> from kohpymc import CalibrationData
        >>> d = MultiOutputData({"a": CalibrationData({"P": [1.0, 2.0]}, [2.0, 3.0])})
        >>> cal, val = d.split(lambda part: part.inputs["P"] < 1.5)
        >>> cal.sizes, val.sizes
        ({'a': 1}, {'a': 1})
        """
        first, second = {}, {}
        for name, part in self.data.items():
            mask = np.asarray(rule(part), dtype=bool)
            if not mask.any() or mask.all():
                raise ValueError(f"split leaves output {name!r} with no rows on one side")
            first[name], second[name] = part.split(mask)
        return MultiOutputData(first), MultiOutputData(second)

    def split_by_range(
        self, name: str, lower: float = -np.inf, upper: float = np.inf
    ) -> tuple[MultiOutputData, MultiOutputData]:
        """Split every output by the range of one input (see ``CalibrationData``)."""
        return self.split(lambda part: (part.inputs[name] >= lower) & (part.inputs[name] <= upper))

    def __repr__(self) -> str:
        noise = {k: ("calibrated" if v is None else f"{v:.4g}") for k, v in self.noise_sd.items()}
        return (
            f"MultiOutputData(outputs={list(self.outputs)}, rows={self.sizes}, "
            f"inputs={list(self.input_names)}, noise_sd={noise})"
        )


def _output_names(outputs: Any) -> tuple[str, ...]:
    if isinstance(outputs, str):
        outputs = [outputs]
    names = tuple(str(o) for o in outputs)
    if not names:
        raise ValueError("give at least one output name")
    repeated = sorted({k for k in names if names.count(k) > 1})
    if repeated:
        raise ValueError(f"output name(s) {repeated} given more than once")
    bad = [k for k in names if not k.isidentifier()]
    if bad:
        raise ValueError(f"output names must be identifiers (they prefix variable names): {bad}")
    return names
