"""Identifiability checks of a calibration formulation, read from its PyMC model.

:func:`check_formulation` / :func:`model_taylor_check` differentiate the mean of the
observed ``y`` (``G + μ_δ`` for M1–M3, ``G + m`` for the GPs) with respect to the
physics and discrepancy-mean parameters on their natural scale, through the model graph,
and analyse the rank with :func:`~kohpymc.identifiability.rank.analyse_matrix`.  The
helpers here (likelihood parts, flattened parameter names, expansion points, Jacobians)
are shared with :mod:`kohpymc.identifiability.fisher`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from kohpymc.identifiability.rank import RTOL, IdentifiabilityReport, analyse_matrix
from kohpymc.model import compose_model
from kohpymc.physics.errors import PhysicsModelError
from kohpymc.physics.spec import singularity_offsets

__all__ = ["check_formulation", "mark_structural", "model_taylor_check"]


@functools.cache
def _one_shot_mode():
    """PyTensor mode of the functions compiled here, each evaluated once or twice.

    FAST_RUN's rewrites (so the same graph and the same numbers as the default mode) with
    the Python linker: no C code is generated, so an empty compile cache costs no g++
    runs here (on the beam study the default C backend compiled 24 modules for these
    functions, ~15 s of g++ with an empty cache).
    """
    from pytensor.compile.mode import Mode

    return Mode(linker="py", optimizer="fast_run")


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


def _free_names(model, rvs, start=None) -> list[tuple[Any, str, int | None]]:
    """Flattened (rv, label, index) per scalar entry of the given free RVs.

    ``start`` is ``model.initial_point()`` when the caller has it (each call compiles).
    """
    out: list[tuple[Any, str, int | None]] = []
    start = model.initial_point() if start is None else start
    for rv in rvs:
        dims = model.named_vars_to_dims.get(rv.name)
        size = int(np.prod(start[model.rvs_to_values[rv].name].shape))
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


def _natural_point(model, point: Mapping[str, Any] | None, start=None) -> dict[str, np.ndarray]:
    """Values of every free RV (natural scale) at ``point`` (default: prior centre).

    ``start`` is ``model.initial_point()`` when the caller has it (each call compiles).
    """
    import pytensor

    start = model.initial_point() if start is None else start
    natural = model.replace_rvs_by_values(model.free_RVs)
    fn = pytensor.function(
        model.value_vars, natural, on_unused_input="ignore", mode=_one_shot_mode()
    )
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

    rvs = list(model.free_RVs)
    if not rvs:
        return
    # one function for every prior (a compile per parameter cost ~0.02-0.1 s each)
    logps = pytensor.function(
        [], [pm.logp(rv, values[rv.name]) for rv in rvs], mode=_one_shot_mode()
    )()
    for rv, lp in zip(rvs, logps, strict=True):
        value = values[rv.name]
        if not np.all(np.isfinite(lp)):
            raise ValueError(
                f"expansion point {rv.name}={value.tolist()} is outside the support of its prior"
            )


def _jacobian(flat, wrt, mode):
    """``d flat / d wrt`` as a ``(flat.size, wrt.size)`` matrix.

    ``mode=None``: ``pytensor.gradient.jacobian`` (its Scan's inner function is compiled
    with the C backend whatever the outer function's mode).  Otherwise the same graph (one
    gradient per row in a Scan) with the inner function compiled in ``mode`` too.
    """
    import pytensor
    import pytensor.tensor as pt
    from pytensor.gradient import grad

    if mode is None:
        return pt.jacobian(flat, wrt, disconnected_inputs="ignore").reshape((flat.size, -1))
    if all(flat.type.broadcastable):
        (jac,) = grad(flat.squeeze(), [wrt], disconnected_inputs="ignore")
    else:
        (jac,) = pytensor.scan(
            lambda idx, expr, w: grad(expr[idx], [w], disconnected_inputs="ignore"),
            sequences=pt.arange(flat.size),
            non_sequences=[flat.ravel(), wrt],
            return_updates=False,
            return_list=True,
            mode=mode,
        )
    return jac.reshape((flat.size, -1))


def _jacobians(model, exprs, rvs, values, mode=None):
    """Evaluate ``d expr / d rv`` (natural scale) for each expression.

    ``mode``: PyTensor mode of the function (default: PyTensor's default mode).
    """
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
        flat = pt.flatten(expr)
        jac = pt.concatenate([_jacobian(flat, inputs[rv], mode) for rv in rvs], axis=1)
        fn = pytensor.function(
            list(inputs.values()), [flat, jac], on_unused_input="ignore", mode=mode
        )
        results.append(fn(*args))
    return results


def _design_point(model, point, start=None):
    import pymc as pm

    if isinstance(point, str):
        if point != "map":
            raise ValueError(f"point must be a mapping, 'map' or None, got {point!r}")
        with model:
            found = pm.find_MAP(progressbar=False)
        return {rv.name: np.asarray(found[rv.name], dtype=float) for rv in model.free_RVs}
    values = _natural_point(model, point, start)
    _check_support(model, values)
    return values


def mean_and_jacobian(model, mu, rvs, values, *, default: bool, fallback=None):
    """``(values, mean, ∂mean/∂rvs)`` at ``values`` (moved off a singularity if ``default``).

    At the default point, next to it when the model is singular there
    (:func:`_off_singularity`), else at ``fallback()`` (physics parameter -> value, e.g.
    :meth:`~kohpymc.PhysicsModel.regular_point` of a model undefined at the prior
    centre) when given; a point the caller chose is used as it is.
    """
    try:
        ((mu_val, A),) = _jacobians(model, [mu], rvs, values, mode=_one_shot_mode())
    except PhysicsModelError:
        found = _moved_point(model, mu, rvs, values, fallback) if default else None
        if found is None:
            raise
        return found
    if default and not np.all(np.isfinite(mu_val)):
        return _moved_point(model, mu, rvs, values, fallback) or (values, mu_val, A)
    return values, mu_val, A


def _moved_point(model, mu, rvs, values, fallback):
    """Off a singularity, else at the ``fallback`` physics point: ``(values, mean, A)``."""
    found = _off_singularity(model, mu, rvs, values)
    if found is not None or fallback is None:
        return found
    try:
        physics_point = fallback()
    except PhysicsModelError:
        return None
    moved = dict(values)
    for name, value in physics_point.items():
        if name in moved:
            moved[name] = np.asarray(value, dtype=float).reshape(moved[name].shape)
    try:
        ((mu_val, A),) = _jacobians(model, [mu], rvs, moved, mode=_one_shot_mode())
    except PhysicsModelError:
        return None
    if np.all(np.isfinite(mu_val)) and np.all(np.isfinite(A)):
        return moved, mu_val, A
    return None


def _off_singularity(model, mu, rvs, values):
    """``(values, mean, A)`` next to ``values`` where the mean is finite, or ``None``.

    The default point can fall on a removable singularity of a correct model
    (``ka / (ka - ke)`` where ``ka`` and ``ke`` have the same prior); each free variable
    is moved by :func:`~kohpymc.physics.spec.singularity_offsets` relative to its value,
    so equal values part, and the first move inside the priors with a finite mean is taken.
    """
    for offsets in singularity_offsets(len(rvs)):
        relative = {rv.name: float(o) for rv, o in zip(rvs, offsets, strict=True)}
        moved = {name: v * (1.0 + relative.get(name, 0.0)) for name, v in values.items()}
        try:
            _check_support(model, moved)
        except ValueError:
            continue
        try:
            ((mu_val, A),) = _jacobians(model, [mu], rvs, moved, mode=_one_shot_mode())
        except PhysicsModelError:
            continue
        if np.all(np.isfinite(mu_val)) and np.all(np.isfinite(A)):
            return moved, mu_val, A
    return None


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
    report = model_taylor_check(built, point=point, rtol=rtol, fallback=regular(physics, data))
    return mark_structural(report, physics, data.inputs, rtol=rtol)


def regular(physics: Any, data: Any) -> Callable[[], dict[str, float]]:
    """``physics.regular_point`` on the data's inputs, to call when the default point fails.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> regular(beam.physics_model(), beam.generate_data(seed=1))()
    {'E': 175.0}
    """
    return lambda: physics.regular_point({k: data.inputs[k] for k in physics.inputs})


def mark_structural(
    report: IdentifiabilityReport,
    physics: Any,
    inputs: Mapping[str, Any],
    *,
    rtol: float = RTOL,
) -> IdentifiabilityReport:
    """Set ``report.structural`` from the physics alone on a denser design, where it can.

    When a confounded set holds physics parameters only, the physics-alone check
    (:func:`~kohpymc.identifiability.physics_check.taylor_check`) is repeated on a
    design ten times denser inside the input ranges at the report's point.  A deficit
    that persists there is structural whatever else is confounded (``True``).  That it
    disappears says "practical" (``False``) only when every confounded set is of physics
    parameters; otherwise ``structural`` stays ``None``.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import CalibrationData, PhysicsModel, Uniform
    >>> x = np.linspace(0.5, 2.0, 8)
    >>> physics = PhysicsModel(lambda i, p: p["a"] * i["x"] / p["b"],
    ...                        {"a": Uniform(0.1, 10.0), "b": Uniform(0.1, 10.0)}, inputs=["x"])
    >>> report = check_formulation(physics, CalibrationData({"x": x}, 3 * x, noise_sd=0.1))
    >>> report.rank, report.structural
    (1, True)
    """
    from kohpymc.identifiability.physics_check import taylor_check

    if report.identifiable:
        return report
    names = set(physics.parameters)
    sets = [set(found) for found in report.non_identifiable_sets]
    if not any(found and found <= names for found in sets):
        return report
    if not all(n in report.point for n in names):
        return report
    point = {n: report.point[n] for n in physics.parameters}
    alone = taylor_check([physics], {k: inputs[k] for k in physics.inputs}, point, rtol=rtol)
    assert isinstance(alone, IdentifiabilityReport)  # one point gives one report
    persists = bool(not alone.identifiable and alone.structural)
    if persists or all(found <= names for found in sets):
        report.structural = persists
    return report


def model_taylor_check(
    built: Any,
    *,
    point: Mapping[str, Any] | str | None = None,
    rtol: float = RTOL,
    fallback: Callable[[], Mapping[str, float]] | None = None,
) -> IdentifiabilityReport:
    """:func:`check_formulation` on an already built unmarginalized calibration model.

    ``built`` is a :class:`~kohpymc.model.CalibrationModel`; the check differentiates
    the mean its formulation's record gives.  ``fallback`` (see :func:`regular`) gives
    the physics parameters' values to use when the mean is non-finite at the default
    point and next to it.

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
    start = model.initial_point()
    values = _design_point(model, point, start)

    ancestors = set(pg.ancestors([mu]))
    rvs = [rv for rv in model.free_RVs if rv in ancestors]
    entries = _free_names(model, rvs, start)
    if len(entries) > n:
        raise ValueError(
            f"design has {n} points for {len(entries)} mean parameters: the rank check "
            "needs at least as many points as parameters"
        )
    values, mu_val, A = mean_and_jacobian(
        model, mu, rvs, values, default=point is None, fallback=fallback
    )
    if not np.all(np.isfinite(mu_val)):
        raise ValueError("the model mean is non-finite at the expansion point")
    flat_point = _flat_point(entries, values)
    return analyse_matrix(A, [e[1] for e in entries], rtol=rtol, point=flat_point)
