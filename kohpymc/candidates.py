"""A library of candidate discrepancy terms built from a model's inputs.

The discovery workflow (issue 5) looks for a missing effect ``c · φ(x)`` among terms made
from the model's own inputs: powers ``x_k^m``, products of two inputs ``x_j x_k``, decaying
exponentials ``exp(-x_k / s)`` at a few fixed scales ``s`` (relative to the input's
range) and logarithms of positive inputs, plus user-supplied terms with a physical meaning.
Each term knows which inputs it depends on and how to print itself ("c * P * x").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["CandidateTerm", "candidate_library", "design_matrix"]

TermFunction = Callable[[Mapping[str, np.ndarray]], np.ndarray]


@dataclass(frozen=True)
class CandidateTerm:
    """One candidate term ``φ(x)`` of a discrepancy ``c · φ(x)``.

    Attributes
    ----------
    name : str
        Short unique name, e.g. ``"P*x"``, ``"x^2"``, ``"exp(-t/25)"``.
    inputs : tuple of str
        Inputs the term depends on.
    function : callable
        ``function(inputs) -> array`` with one value per row.
    decay_scale : float, optional
        For ``exp(-x / s)`` terms: the scale ``s`` the column was built with.  When the
        term is added to a model (:func:`kohpymc.discovery.augmented_physics`) the scale
        becomes a calibrated parameter, so a fixed grid of scales only has to find the
        right order of magnitude.

    Examples
    --------
    >>> import numpy as np
    >>> term = CandidateTerm("P*x", ("P", "x"), lambda d: d["P"] * d["x"])
    >>> term.expression
    'c * P * x'
    >>> term({"P": np.array([2.0]), "x": np.array([3.0])})
    array([6.])
    """

    name: str
    inputs: tuple[str, ...]
    function: TermFunction
    decay_scale: float | None = None

    @property
    def expression(self) -> str:
        """The term with its coefficient, e.g. ``"c * P * x"``."""
        return "c * " + self.name.replace("*", " * ")

    def __call__(self, inputs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Evaluate at the rows of ``inputs``."""
        missing = [k for k in self.inputs if k not in inputs]
        if missing:
            raise KeyError(f"candidate term {self.name!r} needs input(s) {missing}")
        values = np.asarray(self.function(inputs), dtype=float)
        n = len(np.asarray(inputs[self.inputs[0]])) if self.inputs else values.size
        return np.broadcast_to(values, (n,)).astype(float)


def _fmt(value: float) -> str:
    return f"{value:.3g}"


def candidate_library(
    inputs: Mapping[str, np.ndarray],
    names: Sequence[str] | None = None,
    *,
    max_power: int = 3,
    interactions: bool = True,
    exponentials: bool = True,
    logarithms: bool = True,
    exponential_scales: Sequence[float] = (0.05, 0.1, 0.2, 0.4, 0.8),
    extra: Mapping[str, tuple[Sequence[str], TermFunction]] | None = None,
) -> list[CandidateTerm]:
    """Candidate terms from the named inputs (and user terms).

    Parameters
    ----------
    inputs : mapping name -> array
        Input values of the data (used for the exponential scales and to decide which
        inputs are positive or constant).
    names : sequence of str, optional
        Inputs to build terms from; default all of ``inputs``.
    max_power : int
        Powers ``x^1 .. x^max_power`` of each input.
    interactions : bool
        Products ``x_j * x_k`` of two different inputs.
    exponentials : bool
        ``exp(-x / s)`` with ``s = f · range(x)`` for ``f`` in ``exponential_scales``
        (inputs that are non-negative only: a decay from the origin, e.g. in time).
    logarithms : bool
        ``log(x)`` for strictly positive inputs.
    exponential_scales : sequence of float
        Scales ``f`` of the exponentials, as fractions of the input's range.
    extra : mapping name -> (inputs, function), optional
        User terms with physical meaning, e.g. ``{"x^2*P": (["x", "P"], f)}``.

    Returns
    -------
    list of CandidateTerm
        Inputs that take a single value in the data give no terms (they cannot be told
        apart from a constant).

    Examples
    --------
    >>> import numpy as np
    >>> data = {"x": np.linspace(1, 10, 5), "P": np.array([1.0, 1.0, 2.0, 2.0, 3.0])}
    >>> [t.name for t in candidate_library(data, max_power=2, exponentials=False)]
    ['x', 'x^2', 'log(x)', 'P', 'P^2', 'log(P)', 'x*P']
    """
    names = list(inputs) if names is None else list(names)
    missing = [k for k in names if k not in inputs]
    if missing:
        raise KeyError(f"candidate library: input(s) {missing} not in the data")
    if max_power < 1:
        raise ValueError(f"max_power must be at least 1, got {max_power}")
    arrays = {k: np.asarray(inputs[k], dtype=float) for k in names}
    varying = [k for k in names if np.ptp(arrays[k]) > 0]
    terms: list[CandidateTerm] = []
    for k in varying:
        col = arrays[k]
        for m in range(1, max_power + 1):
            name = k if m == 1 else f"{k}^{m}"
            terms.append(CandidateTerm(name, (k,), lambda d, k=k, m=m: np.asarray(d[k]) ** m))
        if exponentials and np.min(col) >= 0:
            for f in exponential_scales:
                s = float(f * np.ptp(col))
                terms.append(
                    CandidateTerm(
                        f"exp(-{k}/{_fmt(s)})",
                        (k,),
                        lambda d, k=k, s=s: np.exp(-np.asarray(d[k]) / s),
                        decay_scale=s,
                    )
                )
        if logarithms and np.min(col) > 0:
            terms.append(CandidateTerm(f"log({k})", (k,), lambda d, k=k: np.log(d[k])))
    if interactions:
        for i, a in enumerate(varying):
            for b in varying[i + 1 :]:
                terms.append(
                    CandidateTerm(f"{a}*{b}", (a, b), lambda d, a=a, b=b: np.asarray(d[a]) * d[b])
                )
    for name, (term_inputs, function) in (extra or {}).items():
        if not callable(function):
            raise TypeError(f"candidate term {name!r}: function is not callable")
        terms.append(CandidateTerm(str(name), tuple(term_inputs), function))
    if not terms:
        raise ValueError(
            "the candidate library is empty: no input varies in the data and no extra terms"
        )
    seen: set[str] = set()
    for t in terms:
        if t.name in seen:
            raise ValueError(f"candidate library: duplicate term name {t.name!r}")
        seen.add(t.name)
    return terms


def design_matrix(terms: Sequence[CandidateTerm], inputs: Mapping[str, np.ndarray]) -> np.ndarray:
    """The ``(n, len(terms))`` matrix of candidate columns; non-finite columns are an error.

    Examples
    --------
    >>> import numpy as np
    >>> terms = candidate_library({"x": np.array([1.0, 2.0])}, max_power=2,
    ...                           exponentials=False, logarithms=False)
    >>> design_matrix(terms, {"x": np.array([1.0, 2.0])})
    array([[1., 1.],
           [2., 4.]])
    """
    cols = []
    for t in terms:
        col = t(inputs)
        if not np.all(np.isfinite(col)):
            bad = int(np.sum(~np.isfinite(col)))
            raise ValueError(f"candidate term {t.name!r} is not finite at {bad} row(s)")
        cols.append(col)
    return np.column_stack(cols)
