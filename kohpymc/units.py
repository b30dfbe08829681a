"""Physical units: parse unit strings, dimension vectors, Buckingham π groups.

A unit is a factor times a product of powers of the SI base units ``m, kg, s, K, A, mol,
cd``; its *dimension vector* holds the seven exponents (as fractions).  The parser reads

* base units ``m kg s K A mol cd``, the gram ``g``, derived units ``N J W Pa V Ohm``
  (also ``Ω``) ``Hz C``, and ``1`` for a dimensionless quantity;
* SI prefixes on any of them (``mm``, ``kN``, ``uA``/``µA``, ``MPa``, ``GHz``; ``kg`` is
  a prefixed gram);
* products (``*``, ``·`` or a space), quotients (``/``, left to right, so ``J/kg/K`` is
  ``J kg⁻¹ K⁻¹``), powers ``^`` or ``**`` with integer, decimal or fractional exponents
  (``m/s^2``, ``kg*m^2``, ``Hz^0.5``, ``m^(1/2)``, ``s^-1``) and parentheses
  (``W/(m*K)``).

:func:`pi_groups` returns a basis of the dimensionless products of a set of quantities
(the null space of their dimension matrix, Buckingham's π theorem) with small integer
exponents.  No dependency beyond the standard library and numpy.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from math import gcd, lcm

import numpy as np

__all__ = [
    "BASE_UNITS",
    "Unit",
    "UnitError",
    "parse_unit",
    "dimension_matrix",
    "pi_groups",
    "format_dimension",
]

#: The SI base units, in the order of a dimension vector.
BASE_UNITS: tuple[str, ...] = ("m", "kg", "s", "K", "A", "mol", "cd")


class UnitError(ValueError):
    """A unit string that cannot be read."""


@dataclass(frozen=True)
class Unit:
    """A factor times SI base units: ``factor · m^d[0] kg^d[1] s^d[2] K^d[3] ...``.

    Examples
    --------
    >>> parse_unit("kN") * parse_unit("m")
    Unit(factor=1000.0, dims=(2, 1, -2, 0, 0, 0, 0))
    """

    factor: float
    dims: tuple[Fraction, ...]

    def __mul__(self, other: Unit) -> Unit:
        return Unit(
            self.factor * other.factor,
            tuple(a + b for a, b in zip(self.dims, other.dims, strict=True)),
        )

    def __truediv__(self, other: Unit) -> Unit:
        return self * other**-1

    def __pow__(self, p: Fraction | int) -> Unit:
        p = Fraction(p)
        return Unit(self.factor ** float(p), tuple(d * p for d in self.dims))

    def __repr__(self) -> str:
        dims = ", ".join(str(d) for d in self.dims)
        return f"Unit(factor={self.factor!r}, dims=({dims}))"

    @property
    def dimensionless(self) -> bool:
        """Whether every exponent is zero."""
        return not any(self.dims)

    def __str__(self) -> str:
        return format_dimension(self.dims)


def _base(i: int) -> tuple[Fraction, ...]:
    return tuple(Fraction(int(j == i)) for j in range(len(BASE_UNITS)))


def _unit(factor: float, **powers: int) -> Unit:
    dims = [Fraction(0)] * len(BASE_UNITS)
    for name, p in powers.items():
        dims[BASE_UNITS.index(name)] = Fraction(p)
    return Unit(factor, tuple(dims))


_ONE = Unit(1.0, tuple(Fraction(0) for _ in BASE_UNITS))
_SYMBOLS: dict[str, Unit] = {
    "m": _unit(1.0, m=1),
    "g": _unit(1e-3, kg=1),
    "s": _unit(1.0, s=1),
    "K": _unit(1.0, K=1),
    "A": _unit(1.0, A=1),
    "mol": _unit(1.0, mol=1),
    "cd": _unit(1.0, cd=1),
    "N": _unit(1.0, kg=1, m=1, s=-2),
    "J": _unit(1.0, kg=1, m=2, s=-2),
    "W": _unit(1.0, kg=1, m=2, s=-3),
    "Pa": _unit(1.0, kg=1, m=-1, s=-2),
    "Hz": _unit(1.0, s=-1),
    "C": _unit(1.0, A=1, s=1),
    "V": _unit(1.0, kg=1, m=2, s=-3, A=-1),
    "Ohm": _unit(1.0, kg=1, m=2, s=-3, A=-2),
    "ohm": _unit(1.0, kg=1, m=2, s=-3, A=-2),
    "Ω": _unit(1.0, kg=1, m=2, s=-3, A=-2),
}
_PREFIXES: dict[str, float] = {
    "Y": 1e24, "Z": 1e21, "E": 1e18, "P": 1e15, "T": 1e12, "G": 1e9, "M": 1e6, "k": 1e3,
    "h": 1e2, "da": 1e1, "d": 1e-1, "c": 1e-2, "m": 1e-3, "u": 1e-6, "µ": 1e-6, "μ": 1e-6,
    "n": 1e-9, "p": 1e-12, "f": 1e-15, "a": 1e-18, "z": 1e-21, "y": 1e-24,
}  # fmt: skip

_TOKEN = re.compile(
    r"(?P<num>\d+(?:\.\d*)?(?:/\d+)?)|(?P<word>[A-Za-zΩµμ]+)|(?P<op>\*\*|[*/^()·-]|\s+)"
)


def _symbol(word: str, text: str) -> Unit:
    """A unit symbol, possibly prefixed (a whole symbol wins: ``m`` is the metre)."""
    if word in _SYMBOLS:
        return _SYMBOLS[word]
    for prefix in sorted(_PREFIXES, key=len, reverse=True):
        rest = word[len(prefix) :]
        if word.startswith(prefix) and rest in _SYMBOLS:
            return Unit(_PREFIXES[prefix], _ONE.dims) * _SYMBOLS[rest]
    known = ", ".join(s for s in _SYMBOLS if s not in ("ohm", "Ω"))
    raise UnitError(f"unknown unit {word!r} in {text!r} (known: {known}, with SI prefixes)")


def _tokens(text: str) -> list[tuple[str, str]]:
    """Numbers, words and operators; a space between two factors becomes ``" "`` (times)."""
    out: list[tuple[str, str]] = []
    pos, space = 0, False
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            raise UnitError(f"cannot read {text[pos:]!r} in unit {text!r}")
        pos = m.end()
        kind = m.lastgroup or "op"
        value = m.group(kind)
        if value.isspace():
            space = bool(out) and (out[-1][0] in ("word", "num") or out[-1][1] == ")")
            continue
        if space and (kind in ("word", "num") or value == "("):
            out.append(("op", " "))
        space = False
        out.append((kind, value))
    return out


class _Parser:
    """``expr := factor ((*|/|·|' ') factor)*``, ``factor := atom (^ exponent)?``."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.toks = _tokens(text)
        self.i = 0

    def peek(self) -> tuple[str, str] | None:
        return self.toks[self.i] if self.i < len(self.toks) else None

    def take(self) -> tuple[str, str]:
        tok = self.peek()
        if tok is None:
            raise UnitError(f"unit {self.text!r} ends too early")
        self.i += 1
        return tok

    def expr(self) -> Unit:
        unit = self.factor()
        while (tok := self.peek()) is not None and tok[0] == "op" and tok[1] in "*/· ":
            self.take()
            rhs = self.factor()
            unit = unit / rhs if tok[1] == "/" else unit * rhs
        return unit

    def factor(self) -> Unit:
        unit = self.atom()
        tok = self.peek()
        if tok is not None and tok[0] == "op" and tok[1] in ("^", "**"):
            self.take()
            unit = unit ** self.exponent()
        return unit

    def exponent(self) -> Fraction:
        sign = 1
        tok = self.take()
        if tok == ("op", "-"):
            sign, tok = -1, self.take()
        if tok == ("op", "("):
            value = self.exponent()
            if self.take() != ("op", ")"):
                raise UnitError(f"missing ')' in the exponent of unit {self.text!r}")
            return sign * value
        if tok[0] != "num":
            raise UnitError(f"expected an exponent after '^' in unit {self.text!r}")
        return sign * Fraction(tok[1]).limit_denominator(1000)

    def atom(self) -> Unit:
        tok = self.take()
        if tok == ("op", "("):
            unit = self.expr()
            if self.take() != ("op", ")"):
                raise UnitError(f"missing ')' in unit {self.text!r}")
            return unit
        if tok[0] == "word":
            return _symbol(tok[1], self.text)
        if tok == ("num", "1"):
            return _ONE
        raise UnitError(f"unexpected {tok[1]!r} in unit {self.text!r}")


def parse_unit(text: str) -> Unit:
    """Read a unit string (see the module docstring for the syntax).

    Parameters
    ----------
    text : str
        E.g. ``"m/s^2"``, ``"kg*m^2"``, ``"W/(m*K)"``, ``"1"`` (dimensionless).

    Returns
    -------
    Unit

    Raises
    ------
    UnitError
        With the offending part of the string.

    Examples
    --------
    >>> str(parse_unit("N*m")), str(parse_unit("J")), parse_unit("mm").factor
    ('kg*m^2/s^2', 'kg*m^2/s^2', 0.001)
    >>> [str(d) for d in parse_unit("m^(1/2)/s").dims[:3]]
    ['1/2', '0', '-1']
    >>> parse_unit("m/sx")
    Traceback (most recent call last):
    ...
    kohpymc.units.UnitError: unknown unit 'sx' in 'm/sx' (known: m, g, s, K, A, mol, cd, N, J, W, Pa, Hz, C, V, Ohm, with SI prefixes)
    """  # noqa: E501
    if not isinstance(text, str) or not text.strip():
        raise UnitError(f"a unit must be a non-empty string, got {text!r}")
    parser = _Parser(text)
    unit = parser.expr()
    if parser.peek() is not None:
        raise UnitError(f"unexpected {parser.peek()[1]!r} in unit {text!r}")  # type: ignore[index]
    return unit


def format_dimension(dims: Sequence[Fraction | float]) -> str:
    """A dimension vector as SI base units, e.g. ``"kg*m/s^2"``; ``"1"`` when dimensionless.

    Examples
    --------
    >>> format_dimension(parse_unit("N").dims), format_dimension(parse_unit("Hz^0.5").dims)
    ('kg*m/s^2', '1/s^(1/2)')
    """
    order = ("kg", "m", "s", "A", "K", "mol", "cd")

    def power(name: str, p: Fraction) -> str:
        if p == 1:
            return name
        return f"{name}^{p}" if p.denominator == 1 else f"{name}^({p})"

    d = {u: Fraction(x).limit_denominator(1000) for u, x in zip(BASE_UNITS, dims, strict=True)}
    num = [power(u, d[u]) for u in order if d[u] > 0]
    den = [power(u, -d[u]) for u in order if d[u] < 0]
    text = "*".join(num) if num else "1"
    if den:
        text += "/" + (den[0] if len(den) == 1 else "(" + "*".join(den) + ")")
    return text


def dimension_matrix(units: Mapping[str, Unit], names: Sequence[str] | None = None) -> np.ndarray:
    """The ``(7, k)`` matrix of dimension exponents, one column per quantity.

    Examples
    --------
    >>> dimension_matrix({"L": parse_unit("m"), "g": parse_unit("m/s^2")})[:3]
    array([[ 1.,  1.],
           [ 0.,  0.],
           [ 0., -2.]])
    """
    names = list(units) if names is None else list(names)
    return np.array([[float(units[k].dims[i]) for k in names] for i in range(len(BASE_UNITS))])


def _rref_null_space(rows: list[list[Fraction]], k: int) -> list[list[Fraction]]:
    """A basis of ``{v : A v = 0}`` in exact arithmetic (one vector per free column)."""
    A = [list(r) for r in rows if any(r)]
    pivots: list[int] = []
    r = 0
    for c in range(k):
        pivot = next((i for i in range(r, len(A)) if A[i][c] != 0), None)
        if pivot is None:
            continue
        A[r], A[pivot] = A[pivot], A[r]
        A[r] = [x / A[r][c] for x in A[r]]
        for i in range(len(A)):
            if i != r and A[i][c] != 0:
                f = A[i][c]
                A[i] = [a - f * b for a, b in zip(A[i], A[r], strict=True)]
        pivots.append(c)
        r += 1
        if r == len(A):
            break
    basis = []
    for free in (c for c in range(k) if c not in pivots):
        v = [Fraction(0)] * k
        v[free] = Fraction(1)
        for i, c in enumerate(pivots):
            v[c] = -A[i][free]
        basis.append(v)
    return basis


def _integers(v: list[Fraction]) -> list[int]:
    """The smallest integer multiple of ``v`` (first non-zero entry positive)."""
    den = lcm(*(x.denominator for x in v))
    ints = [int(x * den) for x in v]
    g = 0
    for x in ints:
        g = gcd(g, abs(x))
    ints = [x // g for x in ints] if g else ints
    first = next((x for x in ints if x), 1)
    return [-x for x in ints] if first < 0 else ints


def pi_groups(
    units: Mapping[str, Unit], names: Sequence[str] | None = None
) -> list[dict[str, int]]:
    """Dimensionless groups ``∏ q_i^{a_i}`` of the quantities (Buckingham's π theorem).

    A basis of the null space of the dimension matrix, found in exact arithmetic and scaled
    to the smallest integer exponents; ``k - rank`` groups for ``k`` quantities.  The basis
    is the one whose free quantities are the last ones (so put the quantities you want to
    see once per group at the end).  Dimensionless quantities are groups by themselves.

    Parameters
    ----------
    units : mapping name -> Unit
        The quantities.
    names : sequence of str, optional
        Their order (default that of ``units``).

    Returns
    -------
    list of dict name -> int
        One dict per group with the non-zero exponents.

    Examples
    --------
    >>> q = {k: parse_unit(u) for k, u in {"T": "s", "L": "m", "g": "m/s^2"}.items()}
    >>> pi_groups(q)                                  # the pendulum: T² g / L
    [{'T': 2, 'L': -1, 'g': 1}]
    >>> drag = {"F": "N", "rho": "kg/m^3", "v": "m/s", "D": "m", "mu": "Pa*s"}
    >>> pi_groups({k: parse_unit(u) for k, u in drag.items()})  # F/(ρ v² D²), F ρ/μ²
    [{'F': 1, 'rho': -1, 'v': -2, 'D': -2}, {'F': 1, 'rho': 1, 'mu': -2}]
    """
    names = list(units) if names is None else list(names)
    rows = [[units[k].dims[i] for k in names] for i in range(len(BASE_UNITS))]
    out = []
    for v in _rref_null_space(rows, len(names)):
        ints = _integers(v)
        out.append({k: p for k, p in zip(names, ints, strict=True) if p})
    return out
