"""The physics model with candidate terms added."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

__all__ = ["augmented_physics"]


def _drift_is_exact(physics, drifts, inputs, theta) -> bool:
    """Whether the physics function takes a parameter that varies per row."""
    if inputs is None or not drifts:
        return True
    x = {k: np.asarray(inputs[k], dtype=float) for k in physics.inputs}
    own = {k: float(theta[k]) for k in physics.parameters}
    try:
        base = np.asarray(physics.function(x, own), dtype=float)
        for _, t in drifts:
            varied = dict(own)
            varied[t.parameter] = own[t.parameter] + np.zeros(base.size)
            out = np.asarray(physics.function(x, varied), dtype=float)
            if out.shape != base.shape or not np.allclose(out, base, rtol=1e-10, atol=0):
                return False
    except Exception:  # noqa: BLE001 - any failure means: not vectorised in θ
        return False
    return True


def augmented_physics(
    physics,
    terms,
    coefficient_sd: Sequence[float],
    *,
    offset_sd: float | None = None,
    inputs: Mapping[str, np.ndarray] | None = None,
    theta: Mapping[str, float] | None = None,
):
    """``G(x; θ) + Σ_k c_k φ_k(x) [+ c_0]`` as a new :class:`~kohpymc.PhysicsModel`.

    The coefficients are parameters ``c_<k>`` with ``Normal(0, coefficient_sd[k])``
    priors.  By kind of term:

    * a drift term ("θ_j varies with x") replaces ``θ_j`` by ``θ_j + c_k g(x)`` inside
      the physics function when the function accepts a parameter that varies per row
      (checked on ``inputs`` at ``theta``), else adds ``c_k (∂G/∂θ_j)(x; θ) g(x)``;
    * an output term multiplies the model by ``1 + c_k g(x)``;
    * any other term is added, a shaped one at its fitted scale.

    ``offset_sd`` adds a constant ``c_0 ~ Normal(0, offset_sd)`` (the constant that is
    part of every explanation, :mod:`kohpymc.discovery.search`).  A user Jacobian of
    ``physics`` is extended with the term columns when all terms are additive; otherwise
    the augmented model uses finite differences.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc.candidates import CandidateTerm
    >>> from kohpymc.examples import beam
    >>> shear = CandidateTerm("x*P", ("x", "P"), lambda d: d["x"] * d["P"])
    >>> aug = augmented_physics(beam.physics_model(), [shear], [1.0])
    >>> aug.parameter_names
    ('E', 'c_1')
    >>> float(aug.evaluate({"x": np.array([400.0]), "P": np.array([2.5])},
    ...                    {"E": 200.0, "c_1": 0.01})[0])
    22.0
    """
    from kohpymc.physics import PhysicsModel

    coefs = _coefficient_names(physics, terms)
    drifts = [(c, t) for c, t in zip(coefs, terms, strict=True) if t.kind == "drift"]
    outputs = [(c, t) for c, t in zip(coefs, terms, strict=True) if t.kind == "output"]
    added = [(c, t) for c, t in zip(coefs, terms, strict=True)
             if t.kind not in ("drift", "output")]  # fmt: skip
    exact = _drift_is_exact(physics, drifts, inputs, theta or physics.prior_mean())
    all_inputs = [*physics.inputs, *(i for t in terms for i in t.inputs)]
    model_inputs = list(dict.fromkeys(all_inputs))
    function = _augmented_function(physics, drifts, outputs, added, exact, offset_sd)
    jacobian = None
    if physics.jacobian is not None and not drifts and not outputs:
        jacobian = _augmented_jacobian(physics, added, offset_sd)
    params = _augmented_priors(physics, coefs, coefficient_sd, offset_sd)
    pieces = [_named(c, t) for c, t in zip(coefs, terms, strict=True)]
    pieces += ["c_0"] if offset_sd is not None else []
    return PhysicsModel(
        function,
        params,
        model_inputs,
        jacobian=jacobian,
        fd_scheme=physics.fd_scheme,
        name=f"{physics.name} + " + " + ".join(pieces),
    )


def _coefficient_names(physics, terms) -> list[str]:
    """``c_1, c_2, ...``, checked against the model (numpy backend, no clashing names)."""
    if physics.backend != "numpy":
        raise NotImplementedError("augmenting a pytensor-backend physics model is not supported")
    coefs = [f"c_{k + 1}" for k in range(len(terms))]
    clash = (set(coefs) | {"c_0"}) & set(physics.parameters)
    if clash:
        raise ValueError(f"augmented model: parameter name(s) {sorted(clash)} already used")
    return coefs


def _augmented_function(physics, drifts, outputs, added, exact: bool, offset_sd: float | None):
    """The augmented model's function: drifts inside (or linearised), outputs, added terms."""
    original, own_names = physics.function, list(physics.parameters)

    def function(x, params):
        own = {k: params[k] for k in own_names}
        xs = {k: x[k] for k in physics.inputs}
        extra = sum(params[c] * t(x) for c, t in added) if added else 0.0
        if exact:
            for c, t in drifts:
                own[t.parameter] = own[t.parameter] + params[c] * t.modulation(x)
        elif drifts:
            J = physics.jacobian_matrix(xs, own)
            for c, t in drifts:
                extra = extra + params[c] * J[:, own_names.index(t.parameter)] * t.modulation(x)
        base = np.asarray(original(xs, own), dtype=float)
        factor = 1.0 + sum(params[c] * t.modulation(x) for c, t in outputs) if outputs else 1.0
        offset = params["c_0"] if offset_sd is not None else 0.0
        return base * factor + extra + offset

    return function


def _augmented_jacobian(physics, added, offset_sd: float | None):
    """The user Jacobian extended by the added terms' columns (and the offset's)."""
    own_names = list(physics.parameters)
    user = physics.jacobian

    def jacobian(x, params):
        J = user({k: x[k] for k in physics.inputs}, {k: params[k] for k in own_names})
        if isinstance(J, dict):
            J = np.column_stack([np.asarray(J[p], dtype=float) for p in own_names])
        cols = [np.asarray(J, dtype=float).reshape(-1, len(own_names))]
        cols += [t(x) for _, t in added]
        if offset_sd is not None:
            cols.append(np.ones(cols[0].shape[0]))
        return np.column_stack(cols)

    return jacobian


def _augmented_priors(
    physics, coefs: Sequence[str], coefficient_sd: Sequence[float], offset_sd: float | None
) -> dict:
    """The model's priors plus ``Normal(0, sd)`` of every coefficient (and of ``c_0``)."""
    from kohpymc.priors import Normal

    params = dict(physics.parameters)
    params.update({c: Normal(0.0, float(s)) for c, s in zip(coefs, coefficient_sd, strict=True)})
    if offset_sd is not None:
        params["c_0"] = Normal(0.0, float(offset_sd))
    return params


def _named(coefficient: str, term) -> str:
    """``"c_1 * x * P"``: the term's expression with its coefficient's name."""
    return term.expression.replace("c *", f"{coefficient} *", 1)
