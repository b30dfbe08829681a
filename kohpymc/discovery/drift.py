"""Candidate terms built from the physics model itself.

* **A parameter varies with an input**: if in truth ``θ_j`` is ``θ_j + c · g(x)`` (a
  resistance that drifts with temperature, a stiffness that softens with amplitude), the
  missing term is, to first order, ``c · (∂G/∂θ_j)(x; θ̂) · g(x)``: the model's own
  sensitivity at the calibrated point times a function of one input.  ``g`` runs over
  the one-input monomials (and ``log``) of :func:`kohpymc.candidates.candidate_library`.
  The term names the effect in the user's words: ``"R depends on T, linearly"``.
* **The output scales with an input**: ``G(x; θ̂) · g(x)``, a multiplicative effect
  ``G · (1 + c · g(x))``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from kohpymc.candidates import DEFAULT_EXPONENTS, CandidateTerm, monomial_name

__all__ = ["physics_terms"]


def _words(k: str, p: float | str) -> str:
    if p == "log":
        return f"logarithmically (as log {k})"
    named = {1.0: "linearly", 2.0: "quadratically", 3.0: "cubically"}
    return named.get(float(p), f"as {monomial_name({k: float(p)})}")


def _modulations(inputs, names, exponents):
    """``(input, label, g)`` for every one-input monomial (and log) allowed on the data."""
    out = []
    for k in names:
        col = np.asarray(inputs[k], dtype=float)
        if np.ptp(col) == 0:
            continue
        positive = np.min(col) > 0
        for p in sorted(set(exponents)):
            if positive or (p > 0 and float(p).is_integer()):
                out.append((k, p, lambda d, k=k, p=p: np.asarray(d[k], dtype=float) ** p))
        if positive:
            out.append((k, "log", lambda d, k=k: np.log(np.asarray(d[k], dtype=float))))
    return out


def _dependence(physics, theta, inputs, G0, J0) -> dict[str, list[str]]:
    """Which of the model's inputs ``G`` and each ``∂G/∂θ_j`` vary with on these rows.

    An input counts when nudging it by 0.1 % of its spread (towards the middle of the
    data) changes the column.
    """
    uses: dict[str, list[str]] = {k: [] for k in ["G", *physics.parameters]}
    for k in physics.inputs:
        col = np.asarray(inputs[k], dtype=float)
        if np.ptp(col) == 0:
            continue
        # nudged towards the middle of the data, never beyond its range (the physics
        # function may refuse inputs outside it, e.g. a position beyond a beam's end)
        step = 1e-3 * np.ptp(col) * np.where(col > np.median(col), -1.0, 1.0)
        nudged = {**inputs, k: col + step}
        G1, J1 = physics.evaluate(nudged, theta), physics.jacobian_matrix(nudged, theta)
        if not np.allclose(G1, G0, rtol=1e-9, atol=0):
            uses["G"].append(k)
        for j, par in enumerate(physics.parameters):
            if not np.allclose(J1[:, j], J0[:, j], rtol=1e-9, atol=0):
                uses[par].append(k)
    return uses


def physics_terms(
    physics,
    theta: Mapping[str, float],
    inputs: Mapping[str, np.ndarray],
    names: Sequence[str] | None = None,
    *,
    exponents: Sequence[float] = DEFAULT_EXPONENTS,
    output: bool = True,
) -> list[CandidateTerm]:
    """Drift terms ``(∂G/∂θ_j) · g(x)`` for every parameter, and output terms ``G · g(x)``.

    Parameters
    ----------
    physics : PhysicsModel
        The model as given.
    theta : mapping
        The calibrated point θ̂.
    inputs : mapping name -> array
        The data's inputs (every recorded input may modulate a parameter, also inputs
        the model ignores).
    names : sequence of str, optional
        Inputs to use; default all of ``inputs``.
    exponents : sequence of float
        Exponents of ``g(x) = x^p``.
    output : bool
        Also offer ``G · g(x)``.

    Returns
    -------
    list of CandidateTerm
        Kinds ``"drift"`` (named ``"R~T"``, ``meaning`` ``"R depends on T, linearly"``)
        and ``"output"`` (named ``"G*T"``).

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import PhysicsModel, Uniform
    >>> ohm = PhysicsModel(lambda x, p: x["I"] * p["R"], {"R": Uniform(1.0, 100.0)}, ["I"])
    >>> data = {"I": np.array([0.1, 0.5, 1.0]), "T": np.array([20.0, 40.0, 60.0])}
    >>> terms = physics_terms(ohm, {"R": 10.0}, data, exponents=(1,), output=False)
    >>> [(t.name, t.inputs, t.meaning) for t in terms][-2]
    ('R~T', ('T', 'I'), 'R depends on T, linearly')
    >>> terms[-2](data)                       # dG/dR * T = I * T
    array([ 2., 20., 60.])
    """
    names = list(inputs) if names is None else list(names)
    theta = {k: float(theta[k]) for k in physics.parameters}
    base = _memoised_base(physics, theta)
    G0, J0 = base(inputs)
    uses = _dependence(physics, theta, inputs, G0, J0)
    terms = _drift_terms(physics, inputs, names, exponents, base, uses)
    if output:
        terms += _output_terms(inputs, names, exponents, base, uses)
    return terms


def _memoised_base(physics, theta: Mapping[str, float]):
    """``d -> (G, ∂G/∂θ)`` at θ̂ on the rows of ``d``, cached for the last inputs."""
    memo: list = []  # [(inputs object, G, ∂G/∂θ)]: the last rows evaluated

    def base(d) -> tuple[np.ndarray, np.ndarray]:
        """``G`` and ``∂G/∂θ`` at θ̂ on the rows of ``d`` (cached for the last inputs)."""
        if not memo or memo[0][0] is not d:
            memo[:] = [(d, physics.evaluate(d, theta), physics.jacobian_matrix(d, theta))]
        return memo[0][1], memo[0][2]

    return base


def _drift_terms(physics, inputs, names, exponents, base, uses) -> list[CandidateTerm]:
    """``(∂G/∂θ_j) · g(x)`` for every parameter and modulation ``g``."""
    terms: list[CandidateTerm] = []
    for j, par in enumerate(physics.parameters):
        for k, p, g in _modulations(inputs, names, exponents):
            label = f"log({k})" if p == "log" else monomial_name({k: float(p)})
            terms.append(
                CandidateTerm(
                    f"{par}~{label}", tuple(dict.fromkeys([k, *uses[par]])),
                    lambda d, j=j, g=g: base(d)[1][:, j] * g(d),  # type: ignore[misc]
                    kind="drift", parameter=par, modulation=g,
                    meaning=f"{par} depends on {k}, {_words(k, p)}", complexity=2,
                    powers={} if p == "log" else {k: float(p)},
                )
            )  # fmt: skip
    return terms


def _output_terms(inputs, names, exponents, base, uses) -> list[CandidateTerm]:
    """``G · g(x)`` for every modulation ``g``."""
    terms: list[CandidateTerm] = []
    for k, p, g in _modulations(inputs, names, exponents):
        label = f"log({k})" if p == "log" else monomial_name({k: float(p)})
        terms.append(
            CandidateTerm(
                f"G*{label}", tuple(dict.fromkeys([k, *uses["G"]])),
                lambda d, g=g: base(d)[0] * g(d), kind="output",  # type: ignore[misc]
                modulation=g, meaning=f"the output scales with {k}, {_words(k, p)}",
                complexity=2, powers={} if p == "log" else {k: float(p)},
            )
        )  # fmt: skip
    return terms
