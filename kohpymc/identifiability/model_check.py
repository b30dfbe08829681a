"""Identifiability checks of a calibration formulation, read from its PyMC model.

:func:`check_formulation` / :func:`model_taylor_check` differentiate the mean of the
observed ``y`` (``G + μ_δ`` for M1–M3, ``G + m`` for the GPs) with respect to the
physics and discrepancy-mean parameters on their natural scale, through the model graph,
and analyse the rank with :func:`~kohpymc.identifiability.rank.analyse_matrix`.  The
helpers here (likelihood parts, flattened parameter names, expansion points, Jacobians)
are shared with :mod:`kohpymc.identifiability.fisher`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from kohpymc.identifiability.rank import RTOL, IdentifiabilityReport, analyse_matrix
from kohpymc.model import compose_model

__all__ = ["check_formulation", "model_taylor_check"]


def _likelihood_parts(built):
    """``(mu, cov_or_sd, is_mv)`` of the observed ``y``, from the formulation's record."""
    import pytensor.tensor as pt

    record = built.likelihood
    if record.covariance is not None:
        return record.mean, record.covariance, True
    if record.variance is not None:
        return record.mean, pt.sqrt(record.variance), False
    label = built.formulation.label or type(built.formulation).__name__
    raise ValueError(
        f"{label}: the Fisher check needs a Gaussian likelihood, and the formulation's "
        "record gives neither a covariance nor variances"
    )


def _free_names(model, rvs) -> list[tuple[Any, str, int | None]]:
    """Flattened (rv, label, index) per scalar entry of the given free RVs."""
    out: list[tuple[Any, str, int | None]] = []
    for rv in rvs:
        dims = model.named_vars_to_dims.get(rv.name)
        size = int(np.prod(model.initial_point()[model.rvs_to_values[rv].name].shape))
        if size == 1 and not dims:
            out.append((rv, rv.name, None))
        else:
            labels = list(model.coords[dims[0]]) if dims else list(range(size))
            out.extend((rv, f"{rv.name}[{labels[k]}]", k) for k in range(size))
    return out


def _flat_point(entries, values: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Scalar value per flattened label (``E``, ``delta_mean[x]``)."""
    return {
        label: float(values[rv.name] if k is None else values[rv.name].reshape(-1)[k])
        for rv, label, k in entries
    }


def _natural_point(model, point: Mapping[str, Any] | None) -> dict[str, np.ndarray]:
    """Values of every free RV (natural scale) at ``point`` (default: prior centre)."""
    import pytensor

    start = model.initial_point()
    natural = model.replace_rvs_by_values(model.free_RVs)
    fn = pytensor.function(model.value_vars, natural, on_unused_input="ignore")
    values = fn(*[start[v.name] for v in model.value_vars])
    out = {
        rv.name: np.asarray(v, dtype=float) for rv, v in zip(model.free_RVs, values, strict=True)
    }
    for key, val in (point or {}).items():
        base = key.split("[")[0]
        if base not in out:
            raise KeyError(f"expansion point names {key!r}, not a parameter of the model")
        out[base] = np.asarray(val, dtype=float).reshape(out[base].shape)
    return out


def _check_support(model, values: Mapping[str, np.ndarray]) -> None:
    """Raise when a value lies outside its prior's support (zero prior density)."""
    import pymc as pm
    import pytensor

    for rv in model.free_RVs:
        value = values[rv.name]
        lp = pytensor.function([], pm.logp(rv, value))()
        if not np.all(np.isfinite(lp)):
            raise ValueError(
                f"expansion point {rv.name}={value.tolist()} is outside the support of its prior"
            )


def _jacobians(model, exprs, rvs, values):
    """Evaluate ``d expr / d rv`` (natural scale) for each expression."""
    import pytensor
    import pytensor.tensor as pt

    inputs = {
        rv: pt.tensor(name=f"{rv.name}_nat", shape=values[rv.name].shape, dtype="float64")
        for rv in model.free_RVs
    }
    replaced = pytensor.clone_replace(list(exprs), replace=dict(inputs))
    results = []
    args = [values[rv.name] for rv in model.free_RVs]
    for expr in replaced:
        cols = [
            pt.jacobian(pt.flatten(expr), inputs[rv], disconnected_inputs="ignore").reshape(
                (expr.size, -1)
            )
            for rv in rvs
        ]
        jac = pt.concatenate(cols, axis=1)
        fn = pytensor.function(
            list(inputs.values()), [pt.flatten(expr), jac], on_unused_input="ignore"
        )
        results.append(fn(*args))
    return results


def _design_point(model, point):
    import pymc as pm

    if isinstance(point, str):
        if point != "map":
            raise ValueError(f"point must be a mapping, 'map' or None, got {point!r}")
        with model:
            found = pm.find_MAP(progressbar=False)
        return {rv.name: np.asarray(found[rv.name], dtype=float) for rv in model.free_RVs}
    values = _natural_point(model, point)
    _check_support(model, values)
    return values


def check_formulation(
    physics: Any,
    data: Any,
    discrepancy: Any = None,
    *,
    point: Mapping[str, Any] | str | None = None,
    rtol: float = RTOL,
) -> IdentifiabilityReport:
    """Taylor check of ``G + m`` for a formulation: physics and discrepancy-mean parameters.

    ``A = ∂μ/∂ψ`` where ``μ`` is the mean of the formulation's likelihood at the data
    inputs (``G + μ_δ`` for M1–M3, ``G + m`` for the GPs) and ψ the physics parameters
    plus the discrepancy-mean coefficients, on their natural scale.  Derivatives come
    from the model graph: the physics model's Jacobian / finite differences for numpy
    models, autodiff otherwise.

    Parameters
    ----------
    physics, data, discrepancy :
        As for :func:`kohpymc.calibrate`.
    point : mapping, "map" or None
        Expansion point: parameter name -> value (others at the prior centre), ``"map"``
        for the MAP estimate, default the prior centre (the paper's prior mean).

    Examples
    --------
    >>> from kohpymc import InputDependentGaussian
    >>> from kohpymc.examples import beam
    >>> report = check_formulation(beam.physics_model(), beam.generate_data(),
    ...                            InputDependentGaussian(mean=["x"]))
    >>> report.identifiable
    True
    """
    built = compose_model(physics, data, discrepancy, marginalize=False)
    return model_taylor_check(built, point=point, rtol=rtol)


def model_taylor_check(
    built: Any, *, point: Mapping[str, Any] | str | None = None, rtol: float = RTOL
) -> IdentifiabilityReport:
    """:func:`check_formulation` on an already built unmarginalized calibration model.

    ``built`` is a :class:`~kohpymc.model.CalibrationModel`; the check differentiates
    the mean its formulation's record gives.

    Examples
    --------
    >>> from kohpymc.model import compose_model
    >>> from kohpymc.examples import beam
    >>> built = compose_model(beam.physics_model(), beam.generate_data(), marginalize=False)
    >>> model_taylor_check(built).names
    ['E']
    """
    import pytensor.graph as pg

    model = built.model
    n = len(model.coords["obs"])
    mu = built.likelihood.mean
    values = _design_point(model, point)

    ancestors = set(pg.ancestors([mu]))
    rvs = [rv for rv in model.free_RVs if rv in ancestors]
    entries = _free_names(model, rvs)
    if len(entries) > n:
        raise ValueError(
            f"design has {n} points for {len(entries)} mean parameters: the rank check "
            "needs at least as many points as parameters"
        )
    ((mu_val, A),) = _jacobians(model, [mu], rvs, values)
    if not np.all(np.isfinite(mu_val)):
        raise ValueError("the model mean is non-finite at the expansion point")
    flat_point = _flat_point(entries, values)
    return analyse_matrix(A, [e[1] for e in entries], rtol=rtol, point=flat_point)
