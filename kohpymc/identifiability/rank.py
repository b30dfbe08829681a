"""Numerical rank of a sensitivity (or Fisher) matrix, and what a deficit means.

Pure numpy.  The columns of ``A`` are first scaled to unit Euclidean norm (so that
parameters of very different magnitude, e.g. E ≈ 200 and φ ≈ 1e-3, cannot fake a rank
drop), then ``r_A`` is the number of singular values above ``rtol · σ_max``.  The default
``rtol = 1e-7`` sits far above central-difference noise (relative error about
``ε^{2/3} ≈ 4e-11``) and far below genuine near-dependence; the condition number
``σ_max / σ_min`` of the scaled matrix is reported alongside so practical
near-non-identifiability is visible too.

Beyond the paper, the null space of ``A`` names *which combination* is confounded (a
direction in ψ along which the output does not change, mapped back from the scaled
coordinates to the parameters' own units: ``Δψ_j = w_j / ‖A_j‖`` for a null vector ``w``
of the scaled matrix), and every minimal set of parameters that cannot be identified
together (the circuits of the column matroid) is listed by a search restricted to the
parameters touched by the null space — no ``p!`` permutations.  :func:`algorithm1` is
the paper's Algorithm 1.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "RTOL",
    "IdentifiabilityReport",
    "IdentifiabilityWarning",
    "algorithm1",
    "analyse_matrix",
]

#: singular values below RTOL · σ_max of the column-scaled matrix count as zero
RTOL = 1e-7
#: condition number above which a full-rank report names its weakest direction
WEAK_CONDITION = 1e3


class IdentifiabilityWarning(UserWarning):
    """A formulation is (locally) non-identifiable at the checked point."""


@dataclass
class IdentifiabilityReport:
    """Result of a rank check of a sensitivity (or Fisher information) matrix.

    Attributes
    ----------
    names : list of str
        Parameters, in column order.
    matrix : numpy.ndarray
        The unscaled matrix (``A``, or the Fisher information).
    singular_values : numpy.ndarray
        Singular values of the column-scaled matrix, descending.
    rank : int
        Numerical rank at ``rtol``.
    condition_number : float
        ``σ_max / σ_min`` of the scaled matrix (inf when rank deficient).
    identifiable_set : list of str
        One identifiable set from the paper's Algorithm 1.
    null_directions : list of dict
        One per minimal set: parameter -> coefficient of a direction ``Δψ`` in the
        parameters' own units (largest coefficient ±1) along which the output (the
        likelihood, for the Fisher check) does not change to first order.
    non_identifiable_sets : list of list of str
        Every minimal set of parameters whose columns are linearly dependent.
    structural : bool or None
        ``True`` when the deficit persists on a denser design, ``False`` when it
        disappears (practical), ``None`` when not tested or full rank.
    weak_direction : dict
        At full rank with a condition number above :data:`WEAK_CONDITION`: the direction
        (own units, largest coefficient ±1; parameters contributing less than a tenth of
        the largest scaled coefficient left out) along which the output changes least —
        the practically non-identifiable combination (see :meth:`weakly_informed`).
    point : dict
        The expansion point.
    kind : str
        ``"taylor"`` or ``"fisher"``.
    """

    names: list[str]
    matrix: np.ndarray
    singular_values: np.ndarray
    rank: int
    rtol: float
    condition_number: float
    identifiable_set: list[str]
    null_directions: list[dict[str, float]]
    non_identifiable_sets: list[list[str]]
    point: dict[str, float] = field(default_factory=dict)
    structural: bool | None = None
    kind: str = "taylor"
    weak_direction: dict[str, float] = field(default_factory=dict)

    @property
    def identifiable(self) -> bool:
        """Full column rank."""
        return self.rank == len(self.names)

    def confounded(self) -> list[str]:
        """Plain-language description of each confounded combination.

        For a null direction ``v`` (original units) the output is unchanged to first
        order when the parameters move by ``Δψ ∝ v``.  For a pair ``(a, b)`` the data
        inform only the orthogonal combination ``-v_b·Δa + v_a·Δb``; when that is the
        gradient at the expansion point of a simple form (``a + b``, ``a - b``, ``a·b``,
        ``a/b``, ``a² + b²``, ``a² - b²``) the text says the result is consistent with
        it.  A single point cannot prove such a form, and several can fit at once (at
        ``a = b``, both ``a + b`` and ``a·b``), so every fitting form is listed and none
        is claimed when none fits.
        """
        effect = "likelihood" if self.kind == "fisher" else "output"
        informed = self.informed_combination()
        out = [informed] if informed else []
        for direction in self.null_directions:
            names = list(direction)
            if len(names) == 1:
                out.append(f"{names[0]} has no effect on the {effect} (at this point)")
                continue
            coefs = np.array([direction[n] for n in names], dtype=float)
            ratio = " : ".join(_number(c) for c in coefs / coefs[0])
            text = (
                f"{', '.join(names[:-1])} and {names[-1]} are confounded: changing them in "
                f"the ratio {' : '.join(f'Δ{n}' for n in names)} = {ratio} leaves the "
                f"{effect} unchanged (to first order)"
            )
            if len(names) == 2:
                (a, ca), (b, cb) = direction.items()
                ga, gb = -cb, ca
                informed = _combination({f"Δ{a}": 1.0, f"Δ{b}": gb / ga})
                text += f"; the data inform only {informed}"
                forms = _simple_forms(a, b, ga, gb, self.point)
                if forms:
                    text += f", consistent with their entering only as {' or '.join(forms)}" + (
                        " (indistinguishable at this point)" if len(forms) > 1 else ""
                    )
            if len(names) > 2 or (len(names) == 2 and "consistent with" not in text):
                text += _power_laws(direction, self.point)
            out.append(text)
        return out

    def informed_combination(self) -> str:
        """The one combination the data inform, when three or more parameters share it.

        Over the parameters of the non-identifiable sets, the matrix (sensitivities, or
        the Fisher information) restricted to them may have rank 1 although they are
        three or more: the output depends on them through one combination only, which
        pairwise confoundings state piecemeal (``A·B``, ``A·C``, ``B·C`` for an output
        depending on ``A·B·C``).  For positive parameters it is named as the power law
        whose log the output depends on (exponents from the sensitivities to ``ln x``,
        the first parameter's made 1), otherwise as the linear combination in their own units.
        Empty unless that rank is 1 and the set has three or more parameters.

        Examples
        --------
        >>> A = np.outer(np.linspace(1.0, 2.0, 5), [1 / 2.0, 1 / 3.0, 1 / 4.0])  # y(a·b·c)
        >>> report = analyse_matrix(A, ["a", "b", "c"], point={"a": 2.0, "b": 3.0, "c": 4.0})
        >>> report.informed_combination()
        'the data inform only one combination of a, b, c: a·b·c (to first order)'
        """
        group = sorted({n for names in self.non_identifiable_sets for n in names},
                       key=self.names.index)  # fmt: skip
        if len(group) < 3:
            return ""
        cols = [self.names.index(n) for n in group]
        fisher = self.kind == "fisher"
        block = self.matrix[np.ix_(cols, cols)] if fisher else self.matrix[:, cols]
        point = np.array([float(self.point.get(n, 0.0)) for n in group])
        positive = bool(np.all(point > 0)) and not any("log" in n for n in group)
        if positive:  # sensitivities to ln x
            block = block * point if not fisher else block * np.outer(point, point)
        norms = np.linalg.norm(block, axis=0)
        if not np.all(norms > 0):
            return ""
        singular = np.linalg.svd(block / norms, compute_uv=False)
        if np.sum(singular > self.rtol * singular[0]) != 1:
            return ""
        weights = np.linalg.svd(block)[2][0]
        first = np.flatnonzero(np.abs(weights) > 1e-6 * np.max(np.abs(weights)))[0]
        weights = weights / weights[first]
        if positive:
            combo = "·".join(
                _power(n, int(round(w))) if np.isclose(w, round(w), atol=1e-3) else f"{n}^{w:.3g}"
                for n, w in zip(group, weights, strict=True)
                if abs(w) > 1e-6
            )
        else:
            combo = _combination({n: w for n, w in zip(group, weights, strict=True)})
        return (
            f"the data inform only one combination of {', '.join(group)}: {combo} (to first order)"
        )

    def weakly_informed(self) -> str:
        """The weakest direction of a full-rank but ill-conditioned matrix, in words.

        A practical (not structural) non-identifiability: along ``weak_direction`` the
        output changes ``condition_number`` times less than along the best-informed
        direction (column-scaled), so the data inform mostly the orthogonal combination.
        For two positive parameters ``a, b`` moving as ``Δln a : Δln b = 1 : r`` the
        informed combination is the power law ``a·b^k``, ``k = -1/r``, shown also with
        small integer exponents when ``k`` is within 10 % of a fraction ``p/q``, q ≤ 4.
        Empty when there is no weak direction.
        """
        if not self.weak_direction:
            return ""
        names = list(self.weak_direction)
        coefs = np.array([self.weak_direction[n] for n in names], dtype=float)
        ratio = " : ".join(_number(c) for c in coefs / coefs[0])
        text = (
            f"weakest direction (output sensitivity {self.condition_number:.2g}× below the "
            f"strongest): {' : '.join(f'Δ{n}' for n in names)} = {ratio}"
        )
        if len(names) != 2 or not all(float(self.point.get(n, 0.0)) > 0 for n in names):
            return text + "; the data inform mostly the orthogonal combination"
        (a, ca), (b, cb) = self.weak_direction.items()
        log_a, log_b = ca / float(self.point[a]), cb / float(self.point[b])
        k = -log_a / log_b
        text += (
            f" (Δln {a} : Δln {b} = 1 : {_number(log_b / log_a)}); the data inform mostly "
            f"{a}·{b}^{k:.3g}"
        )
        for q in (1, 2, 3, 4):
            p = round(k * q)
            if p != 0 and abs(p / q - k) <= 0.1 * abs(k):
                text += (
                    f" ≈ ({_power(a, q)}·{_power(b, p)})^(1/{q})"
                    if q > 1
                    else (f" ≈ {a}·{_power(b, p)}")
                )
                break
        return text + " (practically, not structurally, non-identifiable)"

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary."""
        return {
            "kind": self.kind,
            "parameters": list(self.names),
            "rank": int(self.rank),
            "n_parameters": len(self.names),
            "identifiable": self.identifiable,
            "condition_number": float(self.condition_number),
            "singular_values": [float(s) for s in self.singular_values],
            "identifiable_set": list(self.identifiable_set),
            "non_identifiable_sets": [list(s) for s in self.non_identifiable_sets],
            "null_directions": [{k: float(c) for k, c in d.items()} for d in self.null_directions],
            "confounded": self.confounded(),
            "structural": self.structural,
            "weak_direction": {k: float(c) for k, c in self.weak_direction.items()},
            "weakly_informed": self.weakly_informed(),
            "point": {k: float(v) for k, v in self.point.items()},
        }

    def __str__(self) -> str:
        p = len(self.names)
        head = "Fisher information" if self.kind == "fisher" else "Taylor sensitivity"
        lines = [
            f"{head} check: rank {self.rank} of {p} "
            f"({'identifiable' if self.identifiable else 'NOT identifiable'}), "
            f"condition number {self.condition_number:.3g}",
            f"  parameters: {', '.join(self.names)}",
            f"  one identifiable set (Algorithm 1): {', '.join(self.identifiable_set)}",
        ]
        for s in self.non_identifiable_sets:
            lines.append(f"  cannot be identified together: {{{', '.join(s)}}}")
        for c in self.confounded():
            lines.append(f"  {c}")
        if self.weak_direction:
            lines.append(f"  {self.weakly_informed()}")
        if self.structural is not None:
            lines.append(
                "  deficit persists on a denser design: structural"
                if self.structural
                else "  deficit disappears on a denser design: practical (more data needed)"
            )
        return "\n".join(lines)


def _power_laws(direction: Mapping[str, float], point: Mapping[str, float]) -> str:
    """The power laws left unchanged along a null direction of positive parameters, in words.

    A multiplicative confounding (the output depends on ``a·c^0.7`` and ``b·c`` only) shows
    as a null direction with ``Δln a : Δln b : Δln c = 0.7 : 1 : -1``.  Along it every
    product ``x_i · x_j^k_i`` with ``k_i = -Δln x_i / Δln x_j`` is constant to first
    order; ``x_j`` (the pivot) is the one parameter moving against all the others when
    there is one, else the one moving most in relative terms.  Empty unless every
    parameter of the direction is positive at ``point`` and none is on a log scale by
    name (a discrepancy's ``delta_logvar``: its sign carries no meaning).
    """
    names = list(direction)
    if any("log" in n or float(point.get(n, 0.0)) <= 0 for n in names):
        return ""
    logs = np.array([direction[n] / float(point[n]) for n in names])
    logs = logs / np.max(np.abs(logs)) * (1.0 if logs[0] >= 0 else -1.0)
    signs = np.sign(logs)
    lonely = [i for i in range(len(names)) if np.sum(signs == signs[i]) == 1]
    pivot = lonely[0] if len(lonely) == 1 and len(names) > 2 else int(np.argmax(np.abs(logs)))
    laws = []
    for i, name in enumerate(names):
        if i == pivot or logs[i] == 0:
            continue
        k = -logs[i] / logs[pivot]
        if np.isclose(k, 1.0, rtol=1e-3):
            laws.append(f"{name}·{names[pivot]}")
        elif np.isclose(k, -1.0, rtol=1e-3):
            laws.append(f"{name}/{names[pivot]}")
        else:
            laws.append(f"{name}·{names[pivot]}^{k:.3g}")
    relative = " : ".join(f"Δln {n}" for n in names)
    return (
        f"; in relative terms {relative} = {' : '.join(_number(c) for c in logs)}, "
        f"consistent with their entering only through {' and '.join(laws)}"
    )


def _combination(coefs: Mapping[str, float]) -> str:
    """``{"a": 1, "b": -2}`` -> ``"a - 2·b"`` (first coefficient made positive)."""
    items = list(coefs.items())
    sign = 1.0 if items[0][1] >= 0 else -1.0
    parts = []
    for k, (name, c) in enumerate(items):
        c = sign * c
        mag = "" if np.isclose(abs(c), 1.0, rtol=1e-6) else f"{_number(abs(c))}·"
        op = ("-" if c < 0 else "") if k == 0 else (" - " if c < 0 else " + ")
        parts.append(f"{op}{mag}{name}")
    return "".join(parts)


def _power(name: str, p: int) -> str:
    """``a``, ``a^3``, ``a^-2``."""
    return name if p == 1 else f"{name}^{p}"


def _number(c: float) -> str:
    """Three significant digits, ``-0.333``, ``1.5e-08``; exact ``±1`` as ``1``."""
    if np.isclose(abs(c), 1.0, rtol=1e-9, atol=0.0):
        return "-1" if c < 0 else "1"
    return f"{c:.3g}"


#: tolerance on the ratio of gradient components for naming a simple form
_FORM_RTOL = 1e-5


def _simple_forms(a: str, b: str, ga: float, gb: float, point: Mapping[str, float]) -> list[str]:
    """Simple forms ``f(a, b)`` whose gradient at ``point`` is parallel to ``(ga, gb)``.

    Compared through the ratio of components, so parameters of very different
    magnitude (a ≈ 1e5, b ≈ 1e-3) are matched as well as equal ones.
    """
    if ga == 0 or gb == 0:
        return []
    candidates = {
        f"{a} + {b}": (1.0, 1.0),
        f"{a} - {b}": (1.0, -1.0),
    }
    if a in point and b in point:
        va, vb = float(point[a]), float(point[b])
        candidates.update(
            {
                f"{a}·{b}": (vb, va),
                f"{a}/{b}": (vb, -va),
                f"{a}² + {b}²": (va, vb),
                f"{a}² - {b}²": (va, -vb),
            }
        )
    target = gb / ga
    return [
        form
        for form, (ha, hb) in candidates.items()
        if ha != 0 and hb != 0 and abs((hb / ha) / target - 1.0) < _FORM_RTOL
    ]


def _scaled(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norms = np.linalg.norm(A, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    return A / scale, scale


def _rank(A: np.ndarray, rtol: float) -> int:
    if A.shape[1] == 0:
        return 0
    s = np.linalg.svd(_scaled(A)[0], compute_uv=False)
    return int(np.sum(s > rtol * s[0])) if s.size and s[0] > 0 else 0


def algorithm1(A: np.ndarray, *, rtol: float = RTOL) -> list[int]:
    """The paper's Algorithm 1: indices (0-based) of one identifiable parameter set.

    Walks the columns in order and keeps column ``i`` when removing it from the
    remaining block lowers the rank (it is independent of all later columns), until
    ``r_A`` indices are kept; when the loop reaches the last pair the final column is
    kept (the paper's ``i = p - 1`` branch).

    Examples
    --------
    >>> x = np.array([-1.0, 2.0, 3.5, 4.0, 6.0])
    >>> A = np.column_stack([x, x**2, np.ones(5), x])
    >>> algorithm1(A)
    [1, 2, 3]
    """
    A = np.asarray(A, dtype=float)
    p = A.shape[1]
    r_a = _rank(A, rtol)
    kept: list[int] = []
    temp = A
    for i in range(p - 1):
        r1 = _rank(temp, rtol)
        temp = temp[:, 1:]
        r2 = _rank(temp, rtol)
        if r1 > r2:
            kept.append(i)
        if len(kept) == r_a:
            break
        if i == p - 2:
            kept.append(i + 1)
    if p == 1 and r_a == 1:
        kept = [0]
    return kept


def _minimal_dependent_sets(A: np.ndarray, support: list[int], rtol: float, limit: int):
    """Circuits of the column matroid restricted to ``support`` (increasing size)."""
    circuits: list[tuple[int, ...]] = []
    max_size = min(len(support), _rank(A[:, support], rtol) + 1)
    for size in range(1, max_size + 1):
        for combo in itertools.combinations(support, size):
            if any(set(c) <= set(combo) for c in circuits):
                continue
            if _rank(A[:, list(combo)], rtol) < size:
                circuits.append(combo)
                if len(circuits) >= limit:
                    return circuits
    return circuits


def analyse_matrix(
    A: np.ndarray,
    names: Sequence[str],
    *,
    rtol: float = RTOL,
    point: Mapping[str, float] | None = None,
    kind: str = "taylor",
    max_sets: int = 50,
) -> IdentifiabilityReport:
    """Rank, singular values, Algorithm 1, null directions and minimal dependent sets.

    Parameters
    ----------
    A : array, shape (n, p)
        Sensitivity matrix (or any matrix whose column rank is the question).
    names : sequence of str
        Parameter name per column.
    rtol : float
        Relative singular-value tolerance on the column-scaled matrix.

    Examples
    --------
    The paper's toy example (Eqs. 17–18):

    >>> x = np.array([-1.0, 2.0, 3.5, 4.0, 6.0])
    >>> A = np.column_stack([x, x**2, np.ones(5), x])
    >>> report = analyse_matrix(A, ["theta1", "theta2", "phi1", "phi2"])
    >>> report.rank, report.non_identifiable_sets
    (3, [['theta1', 'phi2']])
    """
    A = np.asarray(A, dtype=float)
    names = list(names)
    if A.ndim != 2 or A.shape[1] != len(names):
        raise ValueError(f"matrix of shape {A.shape} does not have {len(names)} columns")
    if not np.all(np.isfinite(A)):
        raise ValueError("the sensitivity matrix has non-finite entries")
    scaled, scale = _scaled(A)
    _, s, vt = np.linalg.svd(scaled, full_matrices=True)
    s_full = np.zeros(len(names))
    s_full[: s.size] = s
    rank = int(np.sum(s_full > rtol * s_full[0])) if s_full[0] > 0 else 0
    cond = float(s_full[0] / s_full[-1]) if s_full[-1] > rtol * s_full[0] else float("inf")
    null = vt[rank:].T  # (p, p - rank) in scaled coordinates
    support = sorted(set(np.flatnonzero(np.any(np.abs(null) > 1e-6, axis=1)).tolist()))
    circuits = _minimal_dependent_sets(A, support, rtol, max_sets) if support else []
    # one sparse null direction per minimal set (the SVD null basis is an arbitrary rotation).
    # The scaled matrix is A·S⁻¹ (S = diag(scale)), i.e. A in the coordinates u = S·ψ; a null
    # vector w of A·S⁻¹ gives A·(S⁻¹w) = 0, so in the parameters' own units Δψ = w / scale.
    directions = []
    for circuit in circuits:
        cols = list(circuit)
        _, _, vt_c = np.linalg.svd(scaled[:, cols])
        v = vt_c[-1] / scale[cols]
        v = v / v[np.argmax(np.abs(v))]
        directions.append({names[j]: float(c) for j, c in zip(cols, v, strict=True)})
    weak: dict[str, float] = {}
    if rank == len(names) and len(names) > 1 and cond > WEAK_CONDITION:
        w = vt[-1]
        keep = np.flatnonzero(np.abs(w) >= 0.1 * np.abs(w).max())
        v = w[keep] / scale[keep]
        v = v / v[np.argmax(np.abs(v))]
        weak = {names[j]: float(c) for j, c in zip(keep, v, strict=True)}
    return IdentifiabilityReport(
        names=names,
        matrix=A,
        singular_values=s_full,
        rank=rank,
        rtol=rtol,
        condition_number=cond,
        identifiable_set=[names[i] for i in algorithm1(A, rtol=rtol)],
        null_directions=directions,
        non_identifiable_sets=[[names[i] for i in c] for c in circuits],
        point=dict(point or {}),
        kind=kind,
        weak_direction=weak,
    )
