"""The PyMC model of ``y_D = G(x; θ) + δ(x) + ε`` for one discrepancy formulation.

:func:`compose_model` assembles data, physics parameters, the noise model and a
formulation's likelihood into a ``pm.Model`` (optionally with prediction variables at new
inputs) and returns it with the formulation's :class:`~kohpymc.discrepancy.Likelihood`
record as a :class:`CalibrationModel`.  Calibration, prediction and the identifiability
checks all start from it; :func:`build_model` returns just the ``pm.Model``.
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import pymc as pm
import pytensor
import pytensor.tensor as pt

from kohpymc.checks import check_physics_model
from kohpymc.data import CalibrationData
from kohpymc.discrepancy.base import Discrepancy, Likelihood, ModelContext
from kohpymc.discrepancy.none import NoDiscrepancy
from kohpymc.physics import PhysicsModel
from kohpymc.priors import HalfNormal, Prior, as_prior

__all__ = [
    "CalibrationModel",
    "build_model",
    "compose_model",
    "new_input_matrix",
    "OBS_DIM",
    "PRED_DIM",
]

OBS_DIM = "obs"
PRED_DIM = "pred"


def _model_inputs(physics: PhysicsModel, discrepancy: Discrepancy, data: CalibrationData):
    names = tuple(dict.fromkeys(physics.inputs + tuple(discrepancy.inputs)))
    missing = [k for k in names if k not in data.inputs]
    if missing:
        where = f" ({data.source})" if data.source else ""
        raise KeyError(
            f"input name(s) {missing} used by the physics model {physics.name!r} or the "
            f"{discrepancy.label or type(discrepancy).__name__} discrepancy are not in the "
            f"data{where}; data inputs are {list(data.input_names)}"
        )
    return names


def _scales(X: np.ndarray, names: tuple[str, ...]):
    center, scale, span = {}, {}, {}
    for j, name in enumerate(names):
        col = X[:, j]
        sd = float(np.std(col))
        rng = float(np.ptp(col))
        fallback = max(abs(float(np.mean(col))), 1.0)
        center[name] = float(np.mean(col))
        scale[name] = sd if sd > 0 else fallback
        span[name] = rng if rng > 0 else fallback
    return center, scale, span


def new_input_matrix(new_inputs: Any, names: tuple[str, ...]) -> np.ndarray:
    """Stack the named columns of new inputs (DataFrame, mapping or data) into a matrix.

    Examples
    --------
    >>> new_input_matrix({"x": [1.0, 2.0], "P": [3.0, 3.0]}, ("x", "P")).shape
    (2, 2)
    """
    if isinstance(new_inputs, CalibrationData):
        new_inputs = new_inputs.inputs
    if isinstance(new_inputs, pd.DataFrame):
        new_inputs = {str(c): new_inputs[c].to_numpy() for c in new_inputs.columns}
    if not isinstance(new_inputs, Mapping):
        raise TypeError("new_inputs must be a DataFrame, a mapping name -> array or data")
    missing = [k for k in names if k not in new_inputs]
    if missing:
        raise KeyError(f"new_inputs lacks input(s) {missing}; needed {list(names)}")
    cols = [np.asarray(new_inputs[k], dtype=float).reshape(-1) for k in names]
    sizes = {k: c.size for k, c in zip(names, cols, strict=True)}
    if len(set(sizes.values())) != 1:
        raise ValueError(f"new_inputs columns have unequal lengths {sizes}")
    if cols[0].size == 0:
        raise ValueError("new_inputs is empty")
    X = np.column_stack(cols)
    if not np.all(np.isfinite(X)):
        raise ValueError("new_inputs contains NaN/inf")
    return X


#: data set -> the physics models already run on it at the prior mean (this process only;
#: weak references, so nothing is kept alive and nothing travels with a pickled model)
_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _check_physics(physics: PhysicsModel, data: CalibrationData) -> None:
    """Run the model once at the prior mean so failures surface before sampling.

    Once per (physics model, data set) in a process: composing the formulations of a
    study on the same data does not run an expensive simulator again (the result at the
    same point is the same).
    """
    checked = _CHECKED.setdefault(data, weakref.WeakSet())
    if physics in checked:
        return
    physics.regular_point({k: data.inputs[k] for k in physics.inputs})
    checked.add(physics)


@dataclass(frozen=True)
class CalibrationModel:
    """A built calibration model and the record its formulation returned.

    Attributes
    ----------
    model : pymc.Model
        The PyMC model (observed ``"y"`` over dim ``"obs"``).
    likelihood : Likelihood
        What the formulation built (mean, covariance or variances, predictor, ...).
    formulation : Discrepancy
        The formulation.
    input_names : tuple of str
        Columns of the input matrix (physics inputs, then extra discrepancy inputs).
    formulation_variables : tuple of str
        Names of the model variables the formulation created.
    """

    model: pm.Model
    likelihood: Likelihood
    formulation: Discrepancy
    input_names: tuple[str, ...]
    formulation_variables: tuple[str, ...]

    def natural_function(self, outputs: list[Any]) -> tuple[Any, list[str]]:
        """Compile ``outputs`` as a function of the free variables they depend on.

        Returns ``(fn, names)``: ``fn(*values)`` takes the natural-scale values of the
        free variables ``names`` (in that order), as a posterior holds them.  Compiled
        by numba when the outputs hold no Python-only Op (numba caches it on disk, and
        the C backend's first compile in a process reads its whole module cache: 3–5 s
        on a well-used machine), else by PyTensor's default (C) backend.
        """
        from pytensor.graph.traversal import ancestors

        from kohpymc.native import python_only_ops

        upstream = set(ancestors(outputs))
        free = [rv for rv in self.model.free_RVs if rv in upstream]
        inputs = [rv.type(name=rv.name) for rv in free]
        replaced = pytensor.clone_replace(
            list(outputs), replace=dict(zip(free, inputs, strict=True))
        )
        mode = None if python_only_ops(replaced) else "NUMBA"
        fn = pytensor.function(inputs, replaced, on_unused_input="ignore", mode=mode)
        return fn, [rv.name for rv in free]


def _noise_sd(data: CalibrationData, noise_sd_prior: Any, y_scale: float):
    """σ_obs: the data's known value, else a ``"sigma_obs"`` parameter."""
    if data.noise_sd is not None:
        return pt.as_tensor_variable(np.float64(data.noise_sd))
    prior = as_prior(noise_sd_prior, name="sigma_obs") if noise_sd_prior else None
    return (prior or HalfNormal(y_scale)).create("sigma_obs")


def _checked_record(record: Any, discrepancy: Discrepancy, model: pm.Model) -> Likelihood:
    """The formulation's record, or an error naming what the formulation did wrong."""
    name = f"{type(discrepancy).__name__}.build"
    if not isinstance(record, Likelihood):
        raise TypeError(
            f"{name} must return a kohpymc.discrepancy.Likelihood record, "
            f"got {type(record).__name__}"
        )
    if record.observed not in model.named_vars or model[record.observed] not in model.observed_RVs:
        raise ValueError(f"{name} did not add the observed variable {record.observed!r}")
    return record


def formulation_context(
    physics: PhysicsModel,
    discrepancy: Discrepancy,
    theta: Any,
    sigma_obs: Any,
    X: np.ndarray,
    y: np.ndarray,
    names: tuple[str, ...],
    *,
    y_scale: float,
    obs_dim: str,
    marginalize: bool,
) -> tuple[ModelContext, Any, Any]:
    """What a formulation is given to build on: ``(ctx, physics_mean, physics_variance)``.

    ``X`` has the columns ``names`` (physics inputs first).  An emulator's predictive
    covariance enters the likelihood covariance of the formulations that accept it; for
    the others its variance adds to the noise.  Shared by :func:`compose_model` and the
    per-output sub-models of :mod:`kohpymc.multi_output`.
    """
    center, scale, span = _scales(X, names)
    n_phys = len(physics.inputs)

    def physics_mean(Xt: pt.TensorVariable) -> pt.TensorVariable:
        return physics.tensor(theta, Xt[:, :n_phys])

    def physics_variance(Xt: pt.TensorVariable) -> pt.TensorVariable | None:
        return physics.variance_tensor(theta, Xt[:, :n_phys])

    X_phys = pt.as_tensor_variable(X[:, :n_phys])
    physics_cov = None
    if discrepancy.accepts_physics_covariance:
        physics_cov = physics.covariance_tensor(theta, X_phys)
    physics_var = None if physics_cov is not None else physics.variance_tensor(theta, X_phys)
    noise_sd = sigma_obs if physics_var is None else pt.sqrt(sigma_obs**2 + physics_var)
    ctx = ModelContext(
        input_names=names,
        X=X,
        y=y,
        G=physics_mean(pt.as_tensor_variable(X)),
        physics_mean=physics_mean,
        noise_sd=noise_sd,
        y_scale=y_scale,
        center=center,
        scale=scale,
        span=span,
        obs_dim=obs_dim,
        marginalize=marginalize,
        measurement_sd=None if physics_var is None else sigma_obs,
        physics_covariance=physics_cov,
    )
    return ctx, physics_mean, physics_variance


def compose_model(
    physics: PhysicsModel,
    data: CalibrationData,
    discrepancy: Discrepancy | None = None,
    *,
    new_inputs: Any = None,
    noise_sd_prior: Prior | dict[str, Any] | None = None,
    marginalize: bool = True,
) -> CalibrationModel:
    """Build the model of ``y_D = G(x; θ) + δ(x) + ε`` and keep the formulation's record.

    Parameters are those of :func:`build_model`.

    Returns
    -------
    CalibrationModel

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> from kohpymc.discrepancy import IIDGaussian
    >>> built = compose_model(beam.physics_model(), beam.generate_data(seed=1), IIDGaussian(),
    ...                       marginalize=False)
    >>> sorted(built.formulation_variables), built.likelihood.independent_rows
    (['delta_mean', 'delta_sd'], True)
    """
    check_physics_model(physics)
    discrepancy = discrepancy if discrepancy is not None else NoDiscrepancy()
    if not isinstance(discrepancy, Discrepancy):
        raise TypeError(f"discrepancy must be a Discrepancy, got {type(discrepancy).__name__}")
    names = _model_inputs(physics, discrepancy, data)
    _check_physics(physics, data)
    X = data.matrix(names)
    y_sd = float(np.std(data.y))
    y_scale = y_sd if y_sd > 0 else max(float(np.max(np.abs(data.y))), 1.0)
    with pm.Model(coords={OBS_DIM: np.arange(data.n)}) as model:
        thetas = [prior.create(name) for name, prior in physics.parameters.items()]
        theta = pt.stack([pt.as_tensor_variable(t, dtype="float64") for t in thetas])
        # a surrogate valid only in a region of θ (an emulator's design) confines the prior
        support = getattr(physics, "support_logp", None)
        support_term = support(theta) if support is not None else None
        if support_term is not None:
            pm.Potential("physics_support", support_term)
        sigma_obs = _noise_sd(data, noise_sd_prior, y_scale)
        before = set(model.named_vars)
        ctx, physics_mean, physics_variance = formulation_context(
            physics, discrepancy, theta, sigma_obs, X, data.y, names,
            y_scale=y_scale, obs_dim=OBS_DIM, marginalize=marginalize,
        )  # fmt: skip
        record = _checked_record(discrepancy.build(ctx), discrepancy, model)
        created = tuple(k for k in model.named_vars if k not in before and k != record.observed)
        if new_inputs is not None:
            _add_predictions(
                model, record, physics_mean, sigma_obs, physics_variance, new_inputs, names
            )
    return CalibrationModel(model, record, discrepancy, names, created)


def _add_predictions(
    model, record, physics_mean, sigma_obs, physics_variance, new_inputs, names
) -> None:
    """``physics``, ``y_model``, ``discrepancy`` and ``y_pred`` over dim ``"pred"``.

    ``y_pred`` adds σ_obs and, for an emulated physics model, the emulator variance at
    the new inputs.
    """
    Xn_values = new_input_matrix(new_inputs, names)
    model.add_coord(PRED_DIM, np.arange(Xn_values.shape[0]))
    Xn = pt.as_tensor_variable(Xn_values)
    G_new = pm.Deterministic("physics", physics_mean(Xn), dims=PRED_DIM)
    y_model = pm.Deterministic("y_model", record.predictor(Xn, G_new), dims=PRED_DIM)
    pm.Deterministic("discrepancy", y_model - G_new, dims=PRED_DIM)
    variance = physics_variance(Xn)
    noise_sd = sigma_obs if variance is None else pt.sqrt(sigma_obs**2 + variance)
    pm.Normal("y_pred", mu=y_model, sigma=noise_sd, dims=PRED_DIM)


def build_model(
    physics: PhysicsModel,
    data: CalibrationData,
    discrepancy: Discrepancy | None = None,
    *,
    new_inputs: Any = None,
    noise_sd_prior: Prior | dict[str, Any] | None = None,
    marginalize: bool = True,
) -> pm.Model:
    """Build the PyMC model of ``y_D = G(x; θ) + δ(x) + ε`` for one formulation.

    Parameters
    ----------
    physics : PhysicsModel
        The physics model and its parameter priors.
    data : CalibrationData
        Calibration data; its ``noise_sd`` (given or from replicates) fixes σ_obs,
        otherwise σ_obs is a parameter ``"sigma_obs"``.
    discrepancy : Discrepancy, optional
        A registered formulation (M0–M6, ...); default :class:`NoDiscrepancy`.
    new_inputs : DataFrame, mapping or CalibrationData, optional
        Also add prediction variables ``physics``, ``discrepancy``, ``y_model``,
        ``y_pred`` (dim ``"pred"``) at these inputs.
    noise_sd_prior : Prior, optional
        Prior of σ_obs when it is unknown; default ``HalfNormal(sd(y))``.
    marginalize : bool
        Integrate linear discrepancy-mean coefficients with normal priors out of the
        likelihood and recover them per draw (default); ``False`` samples them.

    Returns
    -------
    pymc.Model
        Physics parameters are named as declared; the observed variable is ``"y"``
        with dim ``"obs"``.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> from kohpymc.discrepancy import ConstantBias
    >>> model = build_model(beam.physics_model(), beam.generate_data(seed=1), ConstantBias())
    >>> sorted(model.named_vars)
    ['E', 'delta', 'delta_white', 'y']
    """
    return compose_model(
        physics,
        data,
        discrepancy,
        new_inputs=new_inputs,
        noise_sd_prior=noise_sd_prior,
        marginalize=marginalize,
    ).model
