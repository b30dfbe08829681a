"""Candidate discrepancy terms shaped like physics, built from a model's inputs.

The discovery workflow looks for a missing effect ``c · φ(x)`` among terms made from the
model's own inputs:

* **monomials** ``∏ x_i^{p_i}`` of one, two or three inputs with exponents from a
  configurable set (default ``-2, -1, -½, ½, 1, 2, 3, 4``; negative and fractional powers
  only for inputs that are strictly positive on the data), e.g. ``t^3/m``;
* **shifted powers** ``(x - x_ref)^p`` (``p = 2, 3, 4``) for an input whose natural zero
  lies elsewhere (a temperature near 20 °C): the reference is given by the user or, for an
  input whose values stay more than one range away from 0, its median;
* **logarithms** of strictly positive inputs;
* **shaped terms with a fitted scale** ``c``: saturation ``x / (1 + x/c)`` (non-negative
  inputs), threshold ``max(0, x - c)`` and decay ``exp(-(x - x_min)/c)``.  The scale is
  not gridded: the search fits it per term (:mod:`kohpymc.discovery.search`);
* user terms with a physical meaning.

Terms that depend on the physics model itself ("a parameter varies with an input",
"the output scales with an input") are built by :mod:`kohpymc.discovery.drift`.  Each
term knows which inputs it depends on and how to print itself (``"c * t^3/m"``).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

__all__ = [
    "DEFAULT_EXPONENTS",
    "CandidateTerm",
    "candidate_library",
    "design_matrix",
    "monomial_name",
]

TermFunction = Callable[[Mapping[str, np.ndarray]], np.ndarray]
ShapeFunction = Callable[[Mapping[str, np.ndarray], float], np.ndarray]

#: Default exponents of the monomials.
DEFAULT_EXPONENTS: tuple[float, ...] = (-2.0, -1.0, -0.5, 0.5, 1.0, 2.0, 3.0, 4.0)


@dataclass(frozen=True)
class CandidateTerm:
    """One candidate term ``φ(x)`` of a discrepancy ``c · φ(x)``.

    Attributes
    ----------
    name : str
        Short unique name, e.g. ``"t^3/m"``, ``"P*x"``, ``"max(0,T-c)"``.
    inputs : tuple of str
        Inputs the term depends on.
    function : callable
        ``function(inputs) -> array`` with one value per row (for a shaped term: at its
        fitted scale, or at the initial guess before the fit).
    kind : str
        ``"monomial"``, ``"shifted"``, ``"log"``, ``"saturation"``, ``"threshold"``,
        ``"decay"``, ``"drift"``, ``"output"`` or ``"user"``.
    shape : callable, optional
        For a shaped term, ``shape(inputs, c)``: the column as a function of its scale.
    scale, scale_bounds : float, (float, float), optional
        The fitted scale (None before the fit) and the range searched.
    parameter : str, optional
        For a drift term: the physics parameter that varies, ``θ_j → θ_j + c · g(x)``.
    modulation : callable, optional
        For drift and output terms: ``g(x)``.
    meaning : str, optional
        The term in words, e.g. ``"E depends on T, linearly"``.
    complexity : int
        A rough count of symbols (1 per input factor, +1 per non-integer or negative
        exponent, +1 per fitted scale); breaks ties between terms that are equal on the
        data.
    powers : mapping input -> float, optional
        The exponents that give the term's physical unit: ``∏ unit(x_i)^{p_i}`` (a
        monomial's powers; ``{x: p}`` for ``(x - x_ref)^p``, ``{x: 1}`` for saturation and
        threshold, ``{}`` for a logarithm or a decay; for drift and output terms those
        of ``g(x)``).  None when unknown (user terms).

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
    kind: str = "user"
    shape: ShapeFunction | None = None
    scale: float | None = None
    scale_bounds: tuple[float, float] | None = None
    parameter: str | None = None
    modulation: TermFunction | None = None
    meaning: str | None = None
    complexity: int = 1
    powers: Mapping[str, float] | None = None

    @property
    def expression(self) -> str:
        """The term with its coefficient, e.g. ``"c * P * x"``."""
        if self.kind == "drift":
            return f"{self.parameter} -> {self.parameter} + c * {self.name.split('~', 1)[1]}"
        if self.kind == "output":
            return f"G * (1 + c * {self.name.split('*', 1)[1]})"
        return "c * " + self.name.replace("*", " * ")

    def __call__(self, inputs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Evaluate at the rows of ``inputs``."""
        missing = [k for k in self.inputs if k not in inputs]
        if missing:
            raise KeyError(f"candidate term {self.name!r} needs input(s) {missing}")
        values = np.asarray(self.function(inputs), dtype=float)
        n = len(np.asarray(inputs[self.inputs[0]])) if self.inputs else values.size
        return np.broadcast_to(values, (n,)).astype(float)

    def with_scale(self, scale: float) -> CandidateTerm:
        """The shaped term at a fitted scale (name and function updated).

        Examples
        --------
        >>> import numpy as np
        >>> lib = candidate_library({"x": np.linspace(0.0, 4.0, 9)}, exponents=(1.0,),
        ...                         logarithms=False)
        >>> sat = next(t for t in lib if t.kind == "saturation").with_scale(2.0)
        >>> sat.name, float(sat({"x": np.array([2.0])})[0])
        ('x/(1+x/2)', 1.0)
        """
        if self.shape is None:
            raise ValueError(f"candidate term {self.name!r} has no scale to fit")
        shape, c = self.shape, float(scale)
        return dataclasses.replace(
            self,
            name=_shaped_name(self.kind, self.inputs[0], c, self.name),
            function=lambda d: shape(d, c),
            scale=c,
        )


def _fmt(value: float) -> str:
    return f"{value:.3g}"


def _power(name: str, p: float) -> str:
    """``x``, ``x^2``, ``sqrt(x)``, ``x^1.5`` for |p|."""
    q = Fraction(abs(p)).limit_denominator(8)
    if q == 1:
        return name
    if q == Fraction(1, 2):
        return f"sqrt({name})"
    return f"{name}^{q.numerator}" if q.denominator == 1 else f"{name}^{float(q):g}"


def monomial_name(powers: Mapping[str, float]) -> str:
    """``"t^3/m"``, ``"sqrt(x)*P"``, ``"1/(m*L^2)"``: a product of powers as text.

    Examples
    --------
    >>> monomial_name({"t": 3, "m": -1})
    't^3/m'
    >>> monomial_name({"m": -1, "L": -2})
    '1/(m*L^2)'
    """
    num = [_power(k, p) for k, p in powers.items() if p > 0]
    den = [_power(k, p) for k, p in powers.items() if p < 0]
    text = "*".join(num) if num else "1"
    if den:
        text += "/" + (den[0] if len(den) == 1 else "(" + "*".join(den) + ")")
    return text


def _shaped_name(kind: str, k: str, c: float | None, fallback: str) -> str:
    cs = "c" if c is None else _fmt(c)
    if kind == "saturation":
        return f"{k}/(1+{k}/{cs})"
    if kind == "threshold":
        return f"max(0,{k}-{cs})"
    if kind == "decay":
        return fallback.split("/")[0] + f"/{cs})"
    return fallback


def _monomials(arrays, varying, exponents, max_inputs) -> list[CandidateTerm]:
    positive = {k for k in varying if np.min(arrays[k]) > 0}
    terms: list[CandidateTerm] = []
    for size in range(1, max_inputs + 1):
        for combo in itertools.combinations(varying, size):
            allowed = [
                [p for p in exponents if k in positive or (p > 0 and float(p).is_integer())]
                for k in combo
            ]
            for powers in itertools.product(*allowed):
                pw = dict(zip(combo, powers, strict=True))
                odd = sum(1 for p in powers if p < 0 or not float(p).is_integer())
                terms.append(
                    CandidateTerm(
                        monomial_name(pw),
                        combo,
                        lambda d, pw=pw: np.prod(  # type: ignore[misc]
                            [np.asarray(d[k], dtype=float) ** p for k, p in pw.items()], axis=0
                        ),
                        kind="monomial",
                        complexity=size + odd,
                        powers=pw,
                    )
                )
    return terms


def _reference(col: np.ndarray, given: float | None) -> float | None:
    """The reference of a shifted power: given, or the median when 0 is far from the data."""
    if given is not None:
        return float(given)
    lo, hi = float(np.min(col)), float(np.max(col))
    span = hi - lo
    far = lo > span or hi < -span
    return float(np.median(col)) if far and span > 0 else None


def _single_input_shapes(k, col, shapes, references) -> list[CandidateTerm]:
    terms: list[CandidateTerm] = []
    ref = _reference(col, references.get(k))
    if ref is not None:
        for p in (2, 3, 4):
            name = f"({k}-{_fmt(ref)})^{p}"
            terms.append(
                CandidateTerm(
                    name, (k,), lambda d, k=k, r=ref, p=p: (np.asarray(d[k]) - r) ** p,  # type: ignore[misc]
                    kind="shifted", complexity=2, powers={k: float(p)},
                )
            )  # fmt: skip
    lo, hi = float(np.min(col)), float(np.max(col))
    span = hi - lo
    # the scale's range: from a twentieth of the data's range to ten times it
    if "saturation" in shapes and lo >= 0:
        terms.append(
            CandidateTerm(
                _shaped_name("saturation", k, None, ""), (k,),
                lambda d, k=k, c=span: np.asarray(d[k]) / (1 + np.asarray(d[k]) / c),  # type: ignore[misc]
                kind="saturation", powers={k: 1.0},
                shape=lambda d, c, k=k: np.asarray(d[k]) / (1 + np.asarray(d[k]) / c),  # type: ignore[misc]
                scale_bounds=(0.02 * span, 10 * max(span, hi)), complexity=3,
            )
        )  # fmt: skip
    if "threshold" in shapes:
        terms.append(
            CandidateTerm(
                _shaped_name("threshold", k, None, ""), (k,),
                lambda d, k=k, c=0.5 * (lo + hi): np.maximum(0.0, np.asarray(d[k]) - c),  # type: ignore[misc]
                kind="threshold", powers={k: 1.0},
                shape=lambda d, c, k=k: np.maximum(0.0, np.asarray(d[k]) - c),  # type: ignore[misc]
                scale_bounds=(lo + 0.05 * span, hi - 0.15 * span), complexity=3,
            )
        )  # fmt: skip
    if "decay" in shapes:
        origin = 0.0 if lo >= 0 else lo
        head = f"exp(-{k}/" if origin == 0 else f"exp(-({k}-{_fmt(origin)})/"
        terms.append(
            CandidateTerm(
                head + "c)", (k,),
                lambda d, k=k, o=origin, c=0.3 * span: np.exp(-(np.asarray(d[k]) - o) / c),  # type: ignore[misc]
                kind="decay", powers={},
                shape=lambda d, c, k=k, o=origin: np.exp(-(np.asarray(d[k]) - o) / c),  # type: ignore[misc]
                scale_bounds=(0.02 * span, 5 * span), complexity=3,
            )
        )  # fmt: skip
    return terms


def candidate_library(
    inputs: Mapping[str, np.ndarray],
    names: Sequence[str] | None = None,
    *,
    exponents: Sequence[float] = DEFAULT_EXPONENTS,
    max_inputs: int = 3,
    logarithms: bool = True,
    shapes: Sequence[str] = ("saturation", "threshold", "decay"),
    references: Mapping[str, float] | None = None,
    extra: Mapping[str, tuple[Sequence[str], TermFunction]] | None = None,
) -> list[CandidateTerm]:
    """Candidate terms from the named inputs (and user terms).

    Parameters
    ----------
    inputs : mapping name -> array
        Input values of the data (used to decide which inputs are positive or constant,
        and for the ranges of the fitted scales).
    names : sequence of str, optional
        Inputs to build terms from; default all of ``inputs``.
    exponents : sequence of float
        Exponents of each factor of a monomial (0 excluded).  Negative and non-integer
        exponents are used only for inputs that are strictly positive on the data.
    max_inputs : int
        Largest number of different inputs in one monomial (1-3).
    logarithms : bool
        ``log(x)`` for strictly positive inputs.
    shapes : sequence of str
        Shaped terms with a fitted scale: any of ``"saturation"``, ``"threshold"``,
        ``"decay"``.
    references : mapping name -> float, optional
        Reference values of inputs whose natural zero is elsewhere (adds
        ``(x - x_ref)^p``); inputs far from 0 get their median automatically.
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
    >>> lib = candidate_library(data, exponents=(-1, 1, 2), shapes=())
    >>> [t.name for t in lib][:8]
    ['1/x', 'x', 'x^2', '1/P', 'P', 'P^2', '1/(x*P)', 'P/x']
    >>> len(lib)
    17
    """
    names = _library_inputs(inputs, names, exponents, max_inputs, shapes)
    arrays = {k: np.asarray(inputs[k], dtype=float) for k in names}
    varying = [k for k in names if np.ptp(arrays[k]) > 0]
    terms = _monomials(arrays, varying, sorted(set(exponents)), max_inputs)
    for k in varying:
        if logarithms and np.min(arrays[k]) > 0:
            log_k = lambda d, k=k: np.log(d[k])  # type: ignore[misc]  # noqa: E731
            terms.append(CandidateTerm(f"log({k})", (k,), log_k, kind="log", powers={}))
        terms += _single_input_shapes(k, arrays[k], shapes, dict(references or {}))
    terms += _user_terms(extra)
    if not terms:
        raise ValueError(
            "the candidate library is empty: no input varies in the data and no extra terms"
        )
    _check_unique_names(terms)
    return terms


def _library_inputs(
    inputs: Mapping[str, np.ndarray],
    names: Sequence[str] | None,
    exponents: Sequence[float],
    max_inputs: int,
    shapes: Sequence[str],
) -> list[str]:
    """The inputs to build terms from, after checking the library's options."""
    names = list(inputs) if names is None else list(names)
    missing = [k for k in names if k not in inputs]
    if missing:
        raise KeyError(f"candidate library: input(s) {missing} not in the data")
    if not 1 <= max_inputs <= 3:
        raise ValueError(f"max_inputs must be 1, 2 or 3, got {max_inputs}")
    if any(p == 0 for p in exponents):
        raise ValueError("exponents: 0 is not an exponent (the constant is always a candidate)")
    unknown = set(shapes) - {"saturation", "threshold", "decay"}
    if unknown:
        raise ValueError(f"unknown shape(s) {sorted(unknown)}")
    return names


def _user_terms(
    extra: Mapping[str, tuple[Sequence[str], TermFunction]] | None,
) -> list[CandidateTerm]:
    """The user's terms (each function must be callable)."""
    terms = []
    for name, (term_inputs, function) in (extra or {}).items():
        if not callable(function):
            raise TypeError(f"candidate term {name!r}: function is not callable")
        terms.append(CandidateTerm(str(name), tuple(term_inputs), function))
    return terms


def _check_unique_names(terms: Sequence[CandidateTerm]) -> None:
    """No two terms may share a name."""
    seen: set[str] = set()
    for t in terms:
        if t.name in seen:
            raise ValueError(f"candidate library: duplicate term name {t.name!r}")
        seen.add(t.name)


def design_matrix(terms: Sequence[CandidateTerm], inputs: Mapping[str, np.ndarray]) -> np.ndarray:
    """The ``(n, len(terms))`` matrix of candidate columns; non-finite columns are an error.

    Examples
    --------
    >>> import numpy as np
    >>> terms = candidate_library({"x": np.array([1.0, 2.0])}, exponents=(1, 2),
    ...                           logarithms=False, shapes=())
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
