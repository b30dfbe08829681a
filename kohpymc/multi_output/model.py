r"""The joint PyMC model of several outputs sharing θ.

For outputs :math:`k = 1..K`, each with its own rows :math:`x_{k,i}`,

.. math::

    y_{k,i} = G_k(x_{k,i}; \theta) + \delta_k(x_{k,i}) + \varepsilon_{k,i},
    \qquad \varepsilon_{k,i} \sim N(0, \sigma_{obs,k}^2),

one θ, and for each output its own noise sd and its own discrepancy (independent across
outputs by default).  The joint log-likelihood is the sum of the outputs' log-likelihoods.

Every output is built as a named PyMC sub-model (``pm.Model(name=k)``), so a registered
single-output formulation builds unchanged and its variables get the output's prefix:
``u::y`` (observed, dim ``obs_u``), ``u::sigma_obs`` (when calibrated),
``u::delta_mean``, ``strain::delta_eta`` ...  The physics parameters are shared and keep
their names.  A shared-input multi-output GP (:class:`Coregionalized`) instead builds
one joint likelihood over all outputs' rows.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pymc as pm
import pytensor.tensor as pt

from kohpymc.discrepancy.base import Discrepancy, Likelihood
from kohpymc.discrepancy.none import NoDiscrepancy
from kohpymc.model import (
    _add_predictions,
    _check_physics,
    _model_inputs,
    formulation_context,
)
from kohpymc.multi_output.data import MultiOutputData, per_output
from kohpymc.multi_output.physics import MultiOutputPhysics
from kohpymc.priors import HalfNormal, Prior, as_prior

__all__ = [
    "MultiOutputModel",
    "OutputPart",
    "compose_multi_output_model",
    "obs_dim",
    "variable",
]


def obs_dim(output: str) -> str:
    """The data-row dimension of one output: ``obs_<output>``.

    Examples
    --------
    >>> obs_dim("strain")
    'obs_strain'
    """
    return f"obs_{output}"


def variable(output: str, name: str) -> str:
    """The model name of an output's variable: ``<output>::<name>``.

    Examples
    --------
    >>> variable("u", "sigma_obs")
    'u::sigma_obs'
    """
    return f"{output}::{name}"


@dataclass(frozen=True)
class OutputPart:
    """What was built for one output.

    Attributes
    ----------
    name : str
        The output.
    formulation : Discrepancy or None
        Its discrepancy (``None`` for a joint :class:`Coregionalized` discrepancy).
    likelihood : Likelihood or None
        The formulation's record (names inside it are unprefixed; ``observed`` is
        :func:`variable` ``(name, record.observed)``).
    input_names : tuple of str
        Columns of the output's input matrix.
    sigma_obs : TensorVariable
        σ_obs of the output (a constant or the variable ``<name>::sigma_obs``).
    noise_scale : float
        The known σ_obs, else the sd of the output's data: what its sensitivities are
        divided by when outputs are stacked for the identifiability check.
    mean : TensorVariable
        ``E[y_k | model variables]`` at the output's rows.
    """

    name: str
    formulation: Discrepancy | None
    likelihood: Likelihood | None
    input_names: tuple[str, ...]
    sigma_obs: Any
    noise_scale: float
    mean: Any


@dataclass(frozen=True)
class MultiOutputModel:
    """A built joint model: the PyMC model and one :class:`OutputPart` per output.

    Attributes
    ----------
    model : pymc.Model
    parts : dict of str to OutputPart
    joint : Any
        The :class:`Coregionalized` build record, or ``None`` (independent outputs).
    """

    model: pm.Model
    parts: dict[str, OutputPart]
    joint: Any = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def outputs(self) -> tuple[str, ...]:
        """Output names in stacking order."""
        return tuple(self.parts)

    def observed_name(self, output: str) -> str:
        """The observed variable of an output (``u::y``; ``y`` for a joint GP)."""
        if self.joint is not None:
            return "y"
        part = self.parts[output]
        return variable(output, part.likelihood.observed)  # type: ignore[union-attr]


def _formulations(
    discrepancy: Discrepancy | Mapping[str, Discrepancy | None] | None, outputs
) -> dict[str, Discrepancy]:
    chosen = per_output(discrepancy, outputs, "discrepancy")
    out = {}
    for name, disc in chosen.items():
        disc = NoDiscrepancy() if disc is None else disc
        if not isinstance(disc, Discrepancy):
            raise TypeError(
                f"discrepancy of output {name!r} must be a Discrepancy, got {type(disc).__name__}"
            )
        out[name] = disc
    return out


def _sigma_obs(name: str, noise_sd: float | None, prior: Any, y_scale: float):
    """σ_obs of one output: its known value, else ``<name>::sigma_obs`` (in the sub-model)."""
    if noise_sd is not None:
        return pt.as_tensor_variable(np.float64(noise_sd))
    if prior is not None:
        return as_prior(prior, name=variable(name, "sigma_obs")).create("sigma_obs")
    return HalfNormal(y_scale).create("sigma_obs")


def _y_scale(y: np.ndarray) -> float:
    sd = float(np.std(y))
    return sd if sd > 0 else max(float(np.max(np.abs(y))), 1e-300)


def _check_outputs(physics: MultiOutputPhysics, data: MultiOutputData) -> None:
    if not isinstance(physics, MultiOutputPhysics):
        raise TypeError(f"physics must be a MultiOutputPhysics, got {type(physics).__name__}")
    if not isinstance(data, MultiOutputData):
        raise TypeError(f"data must be MultiOutputData, got {type(data).__name__}")
    missing = [k for k in data.outputs if k not in physics.outputs]
    if missing:
        raise KeyError(
            f"data output(s) {missing} are not outputs of the physics model "
            f"{physics.name!r} {list(physics.outputs)}"
        )


def _build_output(
    name: str,
    physics: MultiOutputPhysics,
    data: MultiOutputData,
    disc: Discrepancy,
    theta,
    noise_prior,
    marginalize: bool,
    new_inputs: Any,
) -> OutputPart:
    part_physics = physics.output(name)
    part_data = data[name]
    names = _model_inputs(part_physics, disc, part_data)
    _check_physics(part_physics, part_data)
    X = part_data.matrix(names)
    y_scale = _y_scale(part_data.y)
    with pm.Model(name=name) as sub:
        sub.add_coord(obs_dim(name), np.arange(part_data.n))
        sigma_obs = _sigma_obs(name, part_data.noise_sd, noise_prior, y_scale)
        ctx, physics_mean, physics_variance = formulation_context(
            part_physics, disc, theta, sigma_obs, X, part_data.y, names,
            y_scale=y_scale, obs_dim=obs_dim(name), marginalize=marginalize,
        )  # fmt: skip
        record = disc.build(ctx)
        if not isinstance(record, Likelihood):
            raise TypeError(f"{type(disc).__name__}.build must return a Likelihood record")
        observed = variable(name, record.observed)
        if observed not in sub.named_vars or sub[observed] not in sub.observed_RVs:
            raise ValueError(f"{type(disc).__name__}.build did not add {record.observed!r}")
        if new_inputs is not None:
            _add_predictions(
                sub, record, physics_mean, sigma_obs, physics_variance, new_inputs, names
            )
    scale_k = part_data.noise_sd if part_data.noise_sd is not None else y_scale
    return OutputPart(name, disc, record, names, sigma_obs, float(scale_k), record.mean)


def compose_multi_output_model(
    physics: MultiOutputPhysics,
    data: MultiOutputData,
    discrepancy: Any = None,
    *,
    noise_sd_prior: Prior | dict[str, Any] | Mapping[str, Any] | None = None,
    new_inputs: Mapping[str, Any] | None = None,
    marginalize: bool = True,
) -> MultiOutputModel:
    """Build the joint model of all outputs with one θ.

    Parameters
    ----------
    physics : MultiOutputPhysics
    data : MultiOutputData
        Its outputs are the ones modelled (a subset of the physics outputs).
    discrepancy : Discrepancy, mapping output -> Discrepancy, or Coregionalized, optional
        One formulation for every output (each output gets its own instance of its
        parameters), a formulation per output (missing outputs: none), or a joint
        shared-input multi-output GP.  Default: no discrepancy (M0).
    noise_sd_prior : Prior or mapping output -> Prior, optional
        Prior of σ_obs,k for outputs whose data carry no noise sd; default
        ``HalfNormal(sd(y_k))``.
    new_inputs : mapping output -> inputs, optional
        Add prediction variables ``<k>::physics``, ``<k>::y_model``,
        ``<k>::discrepancy``, ``<k>::y_pred`` over dim ``pred`` (one output at a time:
        every output's predictions share the ``pred`` dimension).
    marginalize : bool
        As for :func:`kohpymc.model.build_model`.

    Returns
    -------
    MultiOutputModel

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> built = compose_multi_output_model(bm.physics_model(), bm.generate_data(seed=1))
    >>> sorted(built.model.named_vars)
    ['E', 'strain::y', 'u::y']
    """
    from kohpymc.multi_output.coregionalized import Coregionalized

    _check_outputs(physics, data)
    outputs = data.outputs
    priors = (
        per_output(noise_sd_prior, outputs, "noise_sd_prior")
        if (isinstance(noise_sd_prior, Mapping) and not _is_prior_table(noise_sd_prior))
        else dict.fromkeys(outputs, noise_sd_prior)
    )
    if new_inputs is not None:
        per_output(new_inputs, outputs, "new_inputs")
        if len(new_inputs) > 1:
            raise ValueError("new_inputs: predict one output per model (they share 'pred')")
    with pm.Model() as model:
        thetas = [prior.create(name) for name, prior in physics.parameters.items()]
        theta = pt.stack([pt.as_tensor_variable(t, dtype="float64") for t in thetas])
        if isinstance(discrepancy, Coregionalized):
            return discrepancy.build_joint(model, physics, data, theta, priors, new_inputs)
        formulations = _formulations(discrepancy, outputs)
        parts = {
            name: _build_output(
                name,
                physics,
                data,
                formulations[name],
                theta,
                priors[name],
                marginalize,
                None if new_inputs is None else new_inputs.get(name),
            )
            for name in outputs
        }
    return MultiOutputModel(model, parts)


def _is_prior_table(value: Mapping[str, Any]) -> bool:
    """``{"prior": "halfnormal", ...}`` is one prior, not a table per output."""
    return "prior" in value
