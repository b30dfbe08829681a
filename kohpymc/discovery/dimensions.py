"""Units in discovery: dimensionless candidate groups and the units of fitted coefficients.

When the units of the inputs and the output are known (``units={"t": "s", "m": "kg",
"output": "m"}``, or ``[data.units]`` in a study file):

* the candidate space also offers the **dimensionless groups** of the inputs
  (Buckingham π, :func:`kohpymc.units.pi_groups`) and their powers from the exponent set —
  a group of four inputs, or with exponents outside the set, is not among the ordinary
  monomials;
* the report states the **unit of each coefficient**, written in the units given
  (``m*kg/s^3``, ``um/(mm*kN)``): for an additive term ``c · φ(x)`` it is
  ``unit(output) / unit(φ)`` (the output's unit for a dimensionless group); for "the
  output scales with x", ``G · (1 + c g(x))``, it is ``1 / unit(g)``; for "θ_j varies
  with x", ``θ_j + c g(x)``, it is ``[θ_j] / unit(g)`` (parameters carry no units in a
  study file); for a user term or an input without a unit it is unknown (None).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from fractions import Fraction

import numpy as np

from kohpymc.candidates import CandidateTerm, monomial_name
from kohpymc.units import Unit, UnitError, parse_unit, pi_groups

__all__ = ["OUTPUT", "read_units", "term_unit", "coefficient_unit", "pi_terms"]

#: The key of the output's unit.
OUTPUT = "output"


def read_units(units: Mapping[str, str], inputs: Sequence[str], where: str = "units"):
    """Parse ``{name: unit string}``; errors name ``where.<key>``.

    Keys are input names and ``"output"``; an unknown key or an unreadable unit is a
    ``ValueError`` naming the key.

    Examples
    --------
    >>> u = read_units({"t": "s", "output": "m"}, ["t", "m"])
    >>> str(u["t"]), str(u["output"])
    ('s', 'm')
    >>> read_units({"t": "sec"}, ["t"])
    Traceback (most recent call last):
    ...
    ValueError: units.t: unknown unit 'sec' in 'sec' (known: m, g, s, K, A, mol, cd, N, J, W, Pa, Hz, C, V, Ohm, with SI prefixes)
    """  # noqa: E501
    out: dict[str, Unit] = {}
    for key, text in units.items():
        if key != OUTPUT and key not in inputs:
            raise ValueError(
                f"{where}.{key}: not an input of the data (inputs: {list(inputs)}) nor {OUTPUT!r}"
            )
        try:
            out[key] = parse_unit(text)
        except UnitError as err:
            raise ValueError(f"{where}.{key}: {err}") from err
    return out


def _power_unit(powers: Mapping[str, float | Fraction], units: Mapping[str, Unit]) -> Unit | None:
    unit = parse_unit("1")
    for k, p in powers.items():
        if k not in units:
            return None
        unit = unit * units[k] ** Fraction(p).limit_denominator(1000)
    return unit


def term_unit(term: CandidateTerm, units: Mapping[str, Unit]) -> Unit | None:
    """Unit of ``φ(x)`` (of ``g(x)`` for drift and output terms); None when unknown.

    Examples
    --------
    >>> from kohpymc.candidates import candidate_library
    >>> import numpy as np
    >>> lib = candidate_library({"t": np.r_[1.0, 2.0], "m": np.r_[1.0, 3.0]}, exponents=(-1, 3))
    >>> t3m = next(t for t in lib if t.name == "t^3/m")
    >>> str(term_unit(t3m, read_units({"t": "s", "m": "kg"}, ["t", "m"])))
    's^3/kg'
    """
    if term.powers is None:
        return None
    return _power_unit(term.powers, units)


def _factor(text: str, p: Fraction) -> str:
    """``s``, ``s^3``, ``(m/s)^2``, ``kg^(1/2)``: one factor of a unit written as given."""
    text = text.strip()
    if any(ch in text for ch in "*/^· ()"):
        text = f"({text})"
    if p == 1:
        return text
    return f"{text}^{p}" if p.denominator == 1 else f"{text}^({p})"


def _quotient(num: list[tuple[str, Fraction]], den: list[tuple[str, Fraction]]) -> str:
    top = [_factor(t, p) for t, p in num if t.strip() != "1"]
    bottom = [_factor(t, p) for t, p in den if t.strip() != "1"]
    text = "*".join(top) if top else "1"
    if bottom:
        text += "/" + (bottom[0] if len(bottom) == 1 else "(" + "*".join(bottom) + ")")
    return text


def coefficient_unit(term: CandidateTerm, units: Mapping[str, str]) -> str | None:
    """Unit of the coefficient ``c`` of a term, written in the units given for the data.

    See the module docstring for the rule per kind of term; None when the term's unit is
    unknown (a user term, or an input without a unit).

    Examples
    --------
    >>> from kohpymc.candidates import CandidateTerm
    >>> units = {"t": "s", "m": "kg", "output": "m"}
    >>> t3m = CandidateTerm("t^3/m", ("t", "m"), lambda d: d["t"] ** 3 / d["m"],
    ...                     kind="monomial", powers={"t": 3, "m": -1})
    >>> coefficient_unit(t3m, units)                      # m / (s^3/kg)
    'm*kg/s^3'
    >>> g_t = CandidateTerm("g~t", ("t",), lambda d: d["t"], kind="drift", parameter="g",
    ...                     powers={"t": 1})
    >>> coefficient_unit(g_t, units)                      # g -> g + c t
    '[g]/s'
    >>> coefficient_unit(t3m, {"t": "ms", "m": "g", "output": "mm"})
    'mm*g/ms^3'
    """
    if term.powers is None or any(k not in units for k in term.powers):
        return None
    pw = {k: Fraction(p).limit_denominator(1000) for k, p in term.powers.items() if p != 0}
    up = [(units[k], p) for k, p in pw.items() if p > 0]  # factors of the term's unit
    down = [(units[k], -p) for k, p in pw.items() if p < 0]
    si = _power_unit(pw, {k: parse_unit(units[k]) for k in pw})
    if si is not None and si.dimensionless and abs(si.factor - 1.0) < 1e-12:
        up, down = [], []  # a dimensionless group: c carries the output's unit
    if term.kind == "drift":
        text = _quotient(down, up)
        head = f"[{term.parameter}]"
        if text == "1":
            return head
        return head + (text[1:] if text.startswith("1/") else "*" + text)
    if term.kind == "output":
        return _quotient(down, up)
    if OUTPUT not in units:
        return None
    return _quotient([(units[OUTPUT], Fraction(1)), *down], up)


def pi_terms(
    inputs: Mapping[str, np.ndarray],
    units: Mapping[str, Unit],
    exponents: Sequence[float],
    *,
    taken: set[str] | None = None,
) -> tuple[list[CandidateTerm], list[dict[str, int]]]:
    """Candidate terms from the dimensionless groups of the inputs, and the groups.

    Only inputs with a unit that vary on the data take part; a group is offered as
    ``Π^p`` for every ``p`` of ``exponents`` (negative and fractional powers only when
    each input of the group is strictly positive).  Terms whose name is in ``taken``
    (already ordinary monomials) are left out.  A dimensionless input is a group of its
    own and already among the monomials, so groups of one input are not offered.

    Examples
    --------
    >>> import numpy as np
    >>> x = {"T": np.r_[1.0, 2.0, 3.0], "L": np.r_[0.5, 1.0, 0.7], "g": np.r_[9.7, 9.8, 9.9]}
    >>> u = read_units({"T": "s", "L": "m", "g": "m/s^2"}, list(x))
    >>> terms, groups = pi_terms(x, u, (1, 2))
    >>> groups, [t.name for t in terms], terms[0].meaning
    ([{'T': 2, 'L': -1, 'g': 1}], ['T^2*g/L', 'T^4*g^2/L^2'], 'the dimensionless group T^2*g/L')
    """
    names = [k for k in inputs if k in units and np.ptp(np.asarray(inputs[k], float)) > 0]
    groups = [g for g in pi_groups({k: units[k] for k in names}, names) if len(g) > 1]
    taken = set(taken or ())
    out: list[CandidateTerm] = []
    for group in groups:
        base = monomial_name({k: float(p) for k, p in group.items()})
        positive = all(np.min(np.asarray(inputs[k], float)) > 0 for k in group)
        for p in sorted(set(exponents)):
            if not positive and (p < 0 or not float(p).is_integer()):
                continue
            pw = {k: float(q) * float(p) for k, q in group.items()}
            name = monomial_name(pw)
            if name in taken:
                continue
            taken.add(name)
            odd = sum(1 for q in pw.values() if q < 0 or not q.is_integer())
            out.append(
                CandidateTerm(
                    name, tuple(group),
                    lambda d, pw=pw: np.prod(  # type: ignore[misc]
                        [np.asarray(d[k], dtype=float) ** q for k, q in pw.items()], axis=0
                    ),
                    kind="pi",
                    meaning=f"the dimensionless group {base}" + ("" if p == 1 else f"^{p:g}"),
                    complexity=len(pw) + odd, powers=pw,
                )
            )  # fmt: skip
    return out, groups
