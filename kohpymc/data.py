r"""Measured data: named inputs, observed output, replicates, known noise, splits.

The measurement-noise standard deviation can be given, or estimated from replicate
measurements with the pooled within-group variance of the paper's Eq. (28):

.. math::

    \sigma_{obs}^2 = \frac{1}{n_1 (n_2 - 1)} \sum_{j=1}^{n_1} \sum_{i=1}^{n_2}
        \Big[D^i_{t_j} - \frac{1}{n_2} \sum_{i=1}^{n_2} D^i_{t_j}\Big]^2

(``n_1`` settings, ``n_2`` replicates each).  With unequal group sizes the divisor
becomes ``Σ_g (n_g - 1)``, which reduces to ``n_1 (n_2 - 1)`` for a balanced design.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping, Sequence
from os import PathLike
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "CalibrationData",
    "NoReplicatesError",
    "non_numeric_entry",
    "row_words",
    "pooled_replicate_sd",
    "read_csv_table",
]

#: the largest magnitude a data value may have: its square (variances, distances) and sums
#: of squares over millions of rows stay finite floats
MAX_ABS_VALUE = 1e150


def _header(path: str | PathLike[str]) -> list[str]:
    """The first row of a CSV file as written (pandas renames repeated names ``x.1``)."""
    with open(path, newline="", encoding="utf-8-sig") as handle:
        return next(csv.reader(handle), [])


def _refuse_other_separator(source: str, header: list[str]) -> None:
    """``ValueError`` when a one-field header holds ``;``, tab or ``|``: not a comma CSV."""
    if len(header) != 1:
        return
    for separator, name in ((";", "';'"), ("\t", "tabs"), ("|", "'|'")):
        if separator in header[0]:
            raise ValueError(
                f"{source}: the header {header[0]!r} looks separated by {name}, not commas; "
                "save the file as comma-separated CSV with '.' as the decimal point"
            )


def read_csv_table(path: str | PathLike[str]) -> pd.DataFrame:
    r"""A CSV data file as a DataFrame; every problem is a ``ValueError`` naming the file.

    Not UTF-8 text, empty, not parseable as CSV, or a column name given twice (which
    pandas would silently rename).  A missing file raises ``FileNotFoundError``.

    Examples
    --------
    >>> import os, tempfile
    >>> path = os.path.join(tempfile.mkdtemp(), "d.csv")
    >>> _ = open(path, "w").write("x,y,x\n1,2,3\n")
    >>> read_csv_table(path)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: .../d.csv: column name(s) ['x'] appear more than once in the header
    """
    source = str(path)
    try:
        header = _header(path)
        frame = pd.read_csv(path, encoding="utf-8")
    except FileNotFoundError as err:
        raise FileNotFoundError(f"data file not found: {source}") from err
    except UnicodeDecodeError as err:
        raise ValueError(
            f"{source}: not UTF-8 text (byte {err.object[err.start]:#04x} at offset {err.start})"
        ) from err
    except pd.errors.EmptyDataError as err:
        raise ValueError(f"{source}: the file is empty (no header row)") from err
    except (pd.errors.ParserError, csv.Error, OSError) as err:
        raise ValueError(f"{source}: cannot be read as CSV: {err}") from err
    _refuse_other_separator(source, header)
    names = [name.strip() for name in header]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"{source}: column name(s) {repeated} appear more than once in the header")
    return frame


class NoReplicatesError(ValueError):
    """Replicates were asked for, but no setting of the data was measured twice."""


def pooled_replicate_sd(values: Sequence[float], groups: Sequence[Any]) -> float:
    """Pooled within-group standard deviation of replicates (paper Eq. 28).

    Parameters
    ----------
    values : array-like
        Measured outputs.
    groups : array-like
        A label per value; values sharing a label are replicates of one setting.

    Returns
    -------
    float
        ``sqrt(Σ_g Σ_i (D_gi - mean_g)² / Σ_g (n_g - 1))``.

    Examples
    --------
    >>> pooled_replicate_sd([1.0, 3.0, 10.0, 12.0], ["a", "a", "b", "b"])
    1.4142135623730951
    """
    values = np.asarray(values, dtype=float).reshape(-1)
    labels = pd.Series(np.asarray(groups, dtype=object).reshape(-1))
    if labels.size != values.size:
        raise ValueError(f"replicates: {labels.size} group labels for {values.size} values")
    frame = pd.DataFrame({"v": values, "g": labels})
    grouped = frame.groupby("g", sort=False)["v"]
    dof = int((grouped.size() - 1).sum())
    if dof < 1:
        raise NoReplicatesError(
            "replicates: no setting has two or more measurements; cannot estimate"
        )
    ss = float(((frame["v"] - grouped.transform("mean")) ** 2).sum())
    return float(np.sqrt(ss / dof))


def row_words(rows: Sequence[int]) -> str:
    """Name data rows, given as 0-based positions after the header, the way a user counts them.

    Parameters
    ----------
    rows : sequence of int
        0-based positions of the rows among the data rows (the header is not a row).

    Returns
    -------
    str
        ``"data row 3 (file line 4 under a header)"``, or for several rows
        ``"data rows 3, 8 (file lines 4, 9 under a header)"``; rows count from 1 after
        the header, as in :func:`non_numeric_entry`.

    Examples
    --------
    >>> row_words([2])
    'data row 3 (file line 4 under a header)'
    >>> row_words([0, 5])
    'data rows 1, 6 (file lines 2, 7 under a header)'
    """
    rows = [int(r) for r in rows]
    if len(rows) == 1:
        return f"data row {rows[0] + 1} (file line {rows[0] + 2} under a header)"
    data = ", ".join(str(r + 1) for r in rows)
    lines = ", ".join(str(r + 2) for r in rows)
    return f"data rows {data} (file lines {lines} under a header)"


def _file_rows(values: Any, positions: Iterable[int]) -> list[int]:
    """The file's data-row positions of ``positions``: a pandas column keeps its rows' labels."""
    index = values.index if isinstance(values, pd.Series | pd.DataFrame) else None
    if index is None or isinstance(index, pd.RangeIndex) or index.dtype.kind not in "iu":
        return [int(p) for p in positions]
    return [int(index[p]) for p in positions]


def non_numeric_entry(values: Any) -> str:
    """Describe the first entry of a column that is not a number, for an error message.

    Parameters
    ----------
    values : array-like
        A column as read from a file or passed in (strings, numbers, missing values).

    Returns
    -------
    str
        ``"'abc' in data row 3 (file line 4 under a header)"``; rows count from 1 after
        the header. Missing values (empty cells, NaN) are not reported.

    Examples
    --------
    >>> non_numeric_entry(["1.5", "2", "abc"])
    "'abc' in data row 3 (file line 4 under a header)"
    """
    column = pd.Series(np.asarray(values, dtype=object).reshape(-1))
    numbers = pd.to_numeric(column, errors="coerce")
    bad = np.flatnonzero((column.notna() & numbers.isna()).to_numpy())
    if not bad.size:
        return "(not found row by row)"
    row = int(bad[0])
    return f"{column.iloc[row]!r} in {row_words(_file_rows(values, [row]))}"


class CalibrationData:
    """Named inputs, one observed output, optional replicates and known noise sd.

    Parameters
    ----------
    inputs : pandas.DataFrame or mapping of str to 1-D array
        One column per input; one row per measurement.
    output : array-like or str
        Observed output ``y_D``; with a DataFrame, a column name (that column is then
        not an input).
    noise_sd : float, optional
        Known measurement-noise standard deviation σ_obs.  When absent and replicates
        are given, it is estimated with Eq. (28); otherwise it is calibrated.
    replicates : array-like or {"inputs"}, optional
        Group label per row (rows sharing a label are repeat measurements of one
        setting), or ``"inputs"`` to group rows whose inputs are identical.
    output_name : str, optional
        Name of the output (default: the column name, else ``"y"``).
    source : str, optional
        Where the data came from (a file name), used in error messages.

    Examples
    --------
    >>> data = CalibrationData({"x": [1.0, 2.0, 3.0]}, [0.9, 2.1, 2.9], noise_sd=0.1)
    >>> data.n, data.input_names
    (3, ('x',))
    """

    def __init__(
        self,
        inputs: pd.DataFrame | Mapping[str, Any],
        output: Any,
        *,
        noise_sd: float | None = None,
        replicates: Any = None,
        output_name: str | None = None,
        source: str | None = None,
    ) -> None:
        where = f" in {source}" if source else ""
        self.source = source
        if isinstance(inputs, pd.DataFrame):
            frame = inputs
            if isinstance(output, str):
                if output not in frame.columns:
                    raise KeyError(
                        f"output column {output!r} not found{where}; columns: {list(frame.columns)}"
                    )
                output_name = output_name or output
                output = frame[output]
                frame = frame.drop(columns=[output_name])
            columns = {str(c): frame[c] for c in frame.columns}  # a Series keeps its file rows
        elif isinstance(inputs, Mapping):
            columns = {str(k): v for k, v in inputs.items()}
        else:
            raise TypeError(
                "inputs must be a pandas DataFrame or a mapping of input name -> 1-D array"
            )
        if not columns:
            raise ValueError(f"data{where} has no input columns")
        self.output_name = output_name or "y"
        y = self._column(output, self.output_name, where)
        if y.size == 0:
            raise ValueError(f"data{where} is empty: no rows")
        arrays: dict[str, np.ndarray] = {}
        for name, values in columns.items():
            arr = self._column(values, name, where)
            if arr.size != y.size:
                raise ValueError(
                    f"input {name!r}{where} has {arr.size} rows but output "
                    f"{self.output_name!r} has {y.size}"
                )
            arrays[name] = arr
        self.inputs: dict[str, np.ndarray] = arrays
        self.y: np.ndarray = y
        self.replicates: np.ndarray | None = None
        if replicates is not None:
            if isinstance(replicates, str) and replicates == "inputs":
                keys = pd.DataFrame(arrays).round(12).astype(str).agg("|".join, axis=1)
                self.replicates = keys.to_numpy(dtype=object)
            else:
                labels = np.asarray(replicates, dtype=object).reshape(-1)
                if labels.size != y.size:
                    raise ValueError(f"replicates{where}: {labels.size} labels for {y.size} rows")
                self.replicates = labels
        self.noise_sd_estimated = False
        if noise_sd is not None:
            noise_sd = float(noise_sd)
            if not (np.isfinite(noise_sd) and noise_sd > 0):
                raise ValueError(
                    f"noise_sd{where} must be a positive finite number, got {noise_sd}"
                )
        elif self.replicates is not None:
            noise_sd = pooled_replicate_sd(y, self.replicates)
            self.noise_sd_estimated = True
        self.noise_sd: float | None = noise_sd

    @staticmethod
    def _column(values: Any, name: str, where: str) -> np.ndarray:
        try:
            arr = np.asarray(values, dtype=float)
        except (TypeError, ValueError) as err:
            raise TypeError(
                f"column {name!r}{where} has a non-numeric value {non_numeric_entry(values)}"
            ) from err
        if arr.ndim != 1:
            arr = arr.reshape(-1) if arr.ndim == 2 and 1 in arr.shape else arr
        if arr.ndim != 1:
            raise ValueError(f"column {name!r}{where} must be 1-D, got shape {arr.shape}")
        bad = ~np.isfinite(arr)
        if bad.any():
            rows = row_words(_file_rows(values, np.flatnonzero(bad)[:5]))
            raise ValueError(
                f"column {name!r}{where} has {int(bad.sum())} NaN/inf value(s) ({rows})"
            )
        if arr.size and np.max(np.abs(arr)) > MAX_ABS_VALUE:
            row = int(np.argmax(np.abs(arr)))
            raise ValueError(
                f"column {name!r}{where} has a value of {arr[row]:.3g} "
                f"({row_words(_file_rows(values, [row]))}): values "
                f"beyond ±{MAX_ABS_VALUE:.0e} overflow when squared; change the column's units"
            )
        return arr

    # ---------------------------------------------------------------- constructors
    @classmethod
    def from_csv(
        cls,
        path: str | PathLike[str],
        *,
        inputs: Sequence[str],
        output: str,
        noise_sd: float | None = None,
        replicates: str | None = None,
    ) -> CalibrationData:
        r"""Read a CSV file with one column per input and one for the output.

        ``replicates`` is a column name of group labels, or ``"inputs"``.

        Examples
        --------
        >>> import io, tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "d.csv")
        >>> _ = open(path, "w").write("x,y\n1,2\n2,4\n")
        >>> CalibrationData.from_csv(path, inputs=["x"], output="y").n
        2
        """
        source = str(path)
        return cls.from_dataframe(
            read_csv_table(path),
            inputs=inputs,
            output=output,
            noise_sd=noise_sd,
            replicates=replicates,
            source=source,
        )

    @classmethod
    def from_dataframe(
        cls,
        frame: pd.DataFrame,
        *,
        inputs: Sequence[str],
        output: str,
        noise_sd: float | None = None,
        replicates: str | None = None,
        source: str | None = None,
    ) -> CalibrationData:
        """Select ``inputs`` and ``output`` columns of a DataFrame.

        Examples
        --------
        >>> import pandas as pd
        >>> df = pd.DataFrame({"x": [1.0, 2.0], "junk": [0, 0], "y": [2.0, 4.0]})
        >>> CalibrationData.from_dataframe(df, inputs=["x"], output="y").input_names
        ('x',)
        """
        where = f" in {source}" if source else ""
        wanted = (
            list(inputs) + [output] + ([replicates] if replicates not in (None, "inputs") else [])
        )
        missing = [c for c in wanted if c not in frame.columns]
        if missing:
            raise KeyError(f"column(s) {missing} not found{where}; columns: {list(frame.columns)}")
        labels = frame[replicates].to_numpy() if replicates not in (None, "inputs") else replicates
        return cls(
            frame[list(inputs)],
            frame[output],
            noise_sd=noise_sd,
            replicates=labels,
            output_name=output,
            source=source,
        )

    # ------------------------------------------------------------------ accessors
    @property
    def n(self) -> int:
        """Number of rows."""
        return int(self.y.size)

    @property
    def input_names(self) -> tuple[str, ...]:
        """Names of the input columns."""
        return tuple(self.inputs)

    def matrix(self, names: Sequence[str]) -> np.ndarray:
        """The ``(n, len(names))`` matrix of the named input columns.

        Examples
        --------
        >>> CalibrationData({"a": [1.0], "b": [2.0]}, [0.0]).matrix(["b", "a"])
        array([[2., 1.]])
        """
        missing = [k for k in names if k not in self.inputs]
        if missing:
            where = f" in {self.source}" if self.source else ""
            raise KeyError(
                f"input(s) {missing} not found in the data{where}; data has {list(self.inputs)}"
            )
        return np.column_stack([self.inputs[k] for k in names])

    def to_dataframe(self) -> pd.DataFrame:
        """Inputs and output as one DataFrame.

        Examples
        --------
        >>> CalibrationData({"x": [1.0]}, [2.0]).to_dataframe().columns.tolist()
        ['x', 'y']
        """
        frame = pd.DataFrame(self.inputs)
        frame[self.output_name] = self.y
        return frame

    # --------------------------------------------------------------------- splits
    def subset(self, mask: Any) -> CalibrationData:
        """Rows selected by a boolean mask (or integer indices), keeping noise settings.

        A noise sd estimated from replicates (Eq. 28) is re-estimated from the selected
        rows' replicates.

        Examples
        --------
        >>> d = CalibrationData({"x": [1.0, 2.0, 3.0]}, [1.0, 2.0, 3.0])
        >>> d.subset([True, False, True]).n
        2
        """
        idx = np.asarray(mask)
        if idx.dtype == bool:
            if idx.shape != (self.n,):
                raise ValueError(f"mask has shape {idx.shape}, data has {self.n} rows")
            idx = np.flatnonzero(idx)
        if idx.size == 0:
            raise ValueError("selection is empty: no rows match")
        new = object.__new__(CalibrationData)
        new.source = self.source
        new.output_name = self.output_name
        new.inputs = {k: v[idx].copy() for k, v in self.inputs.items()}
        new.y = self.y[idx].copy()
        new.replicates = None if self.replicates is None else self.replicates[idx].copy()
        new.noise_sd = self.noise_sd
        new.noise_sd_estimated = self.noise_sd_estimated
        if self.noise_sd_estimated and new.replicates is not None:
            # re-pool (Eq. 28) over the selected rows only, so a calibration subset's
            # noise estimate uses no validation replicates; keep the parent's value when
            # the subset has no replicated setting
            try:
                new.noise_sd = pooled_replicate_sd(new.y, new.replicates)
            except ValueError:
                pass
        return new

    def split(self, mask: Any) -> tuple[CalibrationData, CalibrationData]:
        """Split into ``(rows where mask is True, the rest)``, e.g. calibration/validation.

        Examples
        --------
        >>> d = CalibrationData({"P": [2.5, 2.5, 3.5]}, [1.0, 2.0, 3.0])
        >>> cal, val = d.split(d.inputs["P"] < 3)
        >>> cal.n, val.n
        (2, 1)
        """
        mask = np.asarray(mask, dtype=bool)
        return self.subset(mask), self.subset(~mask)

    def split_by_range(
        self, name: str, lower: float = -np.inf, upper: float = np.inf
    ) -> tuple[CalibrationData, CalibrationData]:
        """Split by the range of one input: ``(lower <= x_name <= upper, the rest)``.

        Examples
        --------
        >>> d = CalibrationData({"P": [2.5, 3.0, 3.5]}, [1.0, 2.0, 3.0])
        >>> cal, val = d.split_by_range("P", upper=3.0)
        >>> val.inputs["P"].tolist()
        [3.5]
        """
        if name not in self.inputs:
            raise KeyError(f"input {name!r} not in the data; data has {list(self.inputs)}")
        if not lower <= upper:
            raise ValueError(f"split_by_range: lower={lower} must be <= upper={upper}")
        values = self.inputs[name]
        return self.split((values >= lower) & (values <= upper))

    def __repr__(self) -> str:
        noise = "calibrated" if self.noise_sd is None else f"{self.noise_sd:.4g}"
        if self.noise_sd_estimated:
            noise += " (Eq. 28)"
        return (
            f"CalibrationData(n={self.n}, inputs={list(self.inputs)}, "
            f"output={self.output_name!r}, noise_sd={noise})"
        )
