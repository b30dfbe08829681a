"""The paper's first-order Taylor check of ``G_new = G + m`` (Eqs. 15–16), physics alone.

For ``G_new(x; ψ) = G(x; θ) + m(x; φ)`` with ``ψ = [θ, φ]`` the sensitivity matrix
``A[i, j] = ∂G_new/∂ψ_j`` at the data inputs and an expansion point ``ψ̂`` decides local
identifiability: rank ``r_A < p`` means the linearised system has infinitely many
solutions.  The additive parts are :class:`~kohpymc.physics.PhysicsModel` objects, each
with its own Jacobian, finite differences or autodiff.  Structural vs practical: when
rank deficient the check is repeated on a denser design; a deficit that persists is
reported as structural.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from kohpymc.identifiability.rank import RTOL, IdentifiabilityReport, _rank, analyse_matrix

__all__ = ["sensitivity_matrix", "taylor_check"]


def sensitivity_matrix(
    models: Sequence[Any],
    inputs: Mapping[str, Any],
    point: Mapping[str, float],
) -> tuple[np.ndarray, list[str]]:
    """``A = ∂(Σ_k model_k)/∂ψ`` at the design ``inputs`` and expansion ``point``.

    Parameters
    ----------
    models : sequence of PhysicsModel
        Additive parts of ``G_new`` (the physics model and, e.g., a discrepancy mean
        written as another :class:`~kohpymc.physics.PhysicsModel`).  Each uses its
        own Jacobian, finite differences (its ``fd_scheme``) or autodiff.
    inputs : mapping
        The design: input name -> 1-D array.
    point : mapping
        Expansion point ψ̂: parameter name -> value.

    Returns
    -------
    (A, names)

    Examples
    --------
    >>> from kohpymc import PhysicsModel, Uniform
    >>> m = PhysicsModel(lambda i, p: p["a"] * i["x"], {"a": Uniform(0, 2)}, inputs=["x"])
    >>> A, names = sensitivity_matrix([m], {"x": [1.0, 2.0]}, {"a": 1.0})
    >>> np.round(A, 6).ravel().tolist(), names
    ([1.0, 2.0], ['a'])
    """
    blocks, names = [], []
    n = None
    for model in models:
        params = {}
        for name, prior in model.parameters.items():
            if name not in point:
                raise KeyError(f"expansion point lacks parameter {name!r}")
            value = float(point[name])
            if not prior.in_support(value):
                raise ValueError(
                    f"expansion point {name}={value:g} is outside the prior support {prior!r}"
                )
            params[name] = value
        values = model.evaluate(inputs, params)  # raises on non-finite output, naming ψ̂
        n = values.size if n is None else n
        blocks.append(model.jacobian_matrix(inputs, params))
        names.extend(model.parameter_names)
    if len(set(names)) != len(names):
        raise ValueError(f"parameter names repeat across the additive parts: {names}")
    A = np.column_stack(blocks)
    if not np.all(np.isfinite(A)):
        raise ValueError(f"non-finite derivatives at the expansion point {dict(point)}")
    if A.shape[0] < A.shape[1]:
        raise ValueError(
            f"design has {A.shape[0]} points for {A.shape[1]} parameters {names}: the rank "
            "check needs at least as many points as parameters"
        )
    return A, names


def _denser_design(inputs: Mapping[str, Any], factor: int, seed: int) -> dict[str, np.ndarray]:
    """A seeded random design ``factor`` times larger, uniform over each input's range."""
    arrays = {k: np.asarray(v, dtype=float).reshape(-1) for k, v in inputs.items()}
    n = next(iter(arrays.values())).size
    rng = np.random.default_rng(seed)
    m = max(factor * n, n + 10)
    return {k: rng.uniform(v.min(), v.max(), size=m) for k, v in arrays.items()}


def taylor_check(
    models: Sequence[Any] | Any,
    inputs: Mapping[str, Any],
    point: Mapping[str, float] | Sequence[Mapping[str, float]] | None = None,
    *,
    rtol: float = RTOL,
    denser: int | None = 10,
    seed: int = 0,
) -> IdentifiabilityReport | list[IdentifiabilityReport]:
    """The paper's first-order Taylor identifiability check, with the extensions.

    Parameters
    ----------
    models : PhysicsModel or sequence of PhysicsModel
        Additive parts of ``G_new = G + m``.
    inputs : mapping
        The data design.
    point : mapping, list of mappings, optional
        Expansion point(s); default the prior mean of every parameter (the paper's
        choice).  Several points check for local non-identifiability.
    rtol : float
        Relative singular-value tolerance (see module docstring).
    denser : int or None
        When rank deficient, repeat on a random design ``denser`` times larger inside
        the input ranges (seeded) to tell structural from practical.

    Returns
    -------
    IdentifiabilityReport, or a list of them for several points.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import PhysicsModel, Normal
    >>> g = PhysicsModel(lambda i, p: p["t1"] * i["x"] + p["t2"] * i["x"] ** 2,
    ...                  {"t1": Normal(2, 1), "t2": Normal(0.5, 1)}, inputs=["x"])
    >>> m = PhysicsModel(lambda i, p: p["p1"] + p["p2"] * i["x"],
    ...                  {"p1": Normal(4, 1), "p2": Normal(1.5, 1)}, inputs=["x"])
    >>> report = taylor_check([g, m], {"x": [-1.0, 2.0, 3.5, 4.0, 6.0]})
    >>> report.rank, report.non_identifiable_sets, report.structural
    (3, [['t1', 'p2']], True)
    """
    models = list(models) if isinstance(models, Sequence) else [models]
    if point is None:
        point = {}
        for model in models:
            point.update(model.prior_mean())
    if not isinstance(point, Mapping):
        return [
            taylor_check(models, inputs, p, rtol=rtol, denser=denser, seed=seed)  # type: ignore[misc]
            for p in point
        ]
    A, names = sensitivity_matrix(models, inputs, point)
    report = analyse_matrix(A, names, rtol=rtol, point=point)
    if not report.identifiable and denser:
        A2, _ = sensitivity_matrix(models, _denser_design(inputs, denser, seed), point)
        report.structural = _rank(A2, rtol) < len(names)
    return report
