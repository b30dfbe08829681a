"""The physics model with candidate terms added."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["augmented_physics"]


def augmented_physics(physics, terms, coefficient_sd: Sequence[float]):
    """``G(x; θ) + Σ_k c_k φ_k(x)`` as a new :class:`~kohpymc.PhysicsModel`.

    The coefficients are parameters ``c_<k>`` with ``Normal(0, coefficient_sd[k])`` priors.
    A decaying exponential ``exp(-x / s)`` (a term with ``decay_scale``) gets its scale as
    a parameter ``tau_<k>`` too, with a ``LogNormal(log s, 0.7)`` prior (a factor 2 either
    way within one sd).  The physics function is called with its own inputs and
    parameters only; a user Jacobian of ``physics`` is extended with the term columns.

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
    from kohpymc.priors import LogNormal, Normal

    if physics.backend != "numpy":
        raise NotImplementedError("augmenting a pytensor-backend physics model is not supported")
    coefs = [f"c_{k + 1}" for k in range(len(terms))]
    taus = {
        k: f"tau_{k + 1}" for k, t in enumerate(terms) if getattr(t, "decay_scale", None)
    }  # fmt: skip
    clash = (set(coefs) | set(taus.values())) & set(physics.parameters)
    if clash:
        raise ValueError(f"augmented model: parameter name(s) {sorted(clash)} already used")
    original = physics.function
    own = list(physics.parameters)
    inputs = list(dict.fromkeys(list(physics.inputs) + [i for t in terms for i in t.inputs]))

    def column(k, t, x, params):
        if k in taus:
            return np.exp(-np.asarray(x[t.inputs[0]], dtype=float) / params[taus[k]])
        return t(x)

    def function(x, params):
        base = original({k: x[k] for k in physics.inputs}, {k: params[k] for k in own})
        extra = sum(
            params[c] * column(k, t, x, params)
            for k, (c, t) in enumerate(zip(coefs, terms, strict=True))
        )
        return base + extra

    jacobian = None
    if physics.jacobian is not None:
        user = physics.jacobian

        def jacobian(x, params):
            J = user({k: x[k] for k in physics.inputs}, {k: params[k] for k in own})
            if isinstance(J, dict):
                J = np.column_stack([np.asarray(J[p], dtype=float) for p in physics.parameters])
            cols = [np.asarray(J, dtype=float).reshape(-1, len(own))]
            cols += [column(k, t, x, params) for k, t in enumerate(terms)]
            for k, tau in taus.items():  # d/dτ c exp(-x/τ) = c x / τ² exp(-x/τ)
                xk = np.asarray(x[terms[k].inputs[0]], dtype=float)
                cols.append(params[coefs[k]] * xk / params[tau] ** 2 * np.exp(-xk / params[tau]))
            return np.column_stack(cols)

    params = dict(physics.parameters)
    params.update({c: Normal(0.0, float(s)) for c, s in zip(coefs, coefficient_sd, strict=True)})
    params.update(
        {tau: LogNormal(float(np.log(terms[k].decay_scale)), 0.7) for k, tau in taus.items()}
    )
    return PhysicsModel(
        function,
        params,
        inputs,
        jacobian=jacobian,
        fd_scheme=physics.fd_scheme,
        name=f"{physics.name} + "
        + " + ".join(
            _named(c, t, taus.get(k)) for k, (c, t) in enumerate(zip(coefs, terms, strict=True))
        ),
    )


def _named(coefficient: str, term, tau: str | None = None) -> str:
    """``"c_1 * x * P"``: the term's expression with its coefficient's (and scale's) name."""
    text = term.expression.replace("c *", f"{coefficient} *", 1)
    if tau is not None:
        text = f"{coefficient} * exp(-{term.inputs[0]}/{tau})"
    return text
