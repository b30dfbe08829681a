r"""Calibrate one θ from several outputs, predict per output, check identifiability.

:func:`calibrate_outputs` builds the joint model
(:func:`~kohpymc.multi_output.model.compose_multi_output_model`), checks
identifiability over the stacked sensitivities of all outputs
(:func:`stacked_taylor_check`), samples it with the package's sampler (nutpie by
default, in whitened coordinates) and returns a :class:`MultiOutputCalibration`.
:func:`predict_output` draws ``<k>::y_model`` and ``<k>::y_pred`` of one output at new
inputs from the joint posterior.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import arviz as az
import numpy as np

from kohpymc.calibration import (
    PHYSICS_PROBLEMS,
    _attach_input_coords,
    posterior_moments,
    problems_at_posterior,
)
from kohpymc.checks import check_compile_mode, resolve_sampler
from kohpymc.diagnostics import SamplerTroubleWarning
from kohpymc.identifiability import IdentifiabilityReport, IdentifiabilityWarning
from kohpymc.identifiability.model_check import (
    _design_point,
    _free_names,
    mean_and_jacobian,
)
from kohpymc.identifiability.rank import RTOL, analyse_matrix
from kohpymc.loo import compute_log_likelihood
from kohpymc.model import PRED_DIM, new_input_matrix
from kohpymc.multi_output.data import MultiOutputData
from kohpymc.multi_output.loo import add_pointwise_log_likelihood
from kohpymc.multi_output.model import (
    MultiOutputModel,
    compose_multi_output_model,
    obs_dim,
    variable,
)
from kohpymc.multi_output.physics import MultiOutputPhysics
from kohpymc.predictive import sample_predictions
from kohpymc.sampling import SamplingReport, one_blas_thread, sample_posterior
from kohpymc.second_run import run_problems
from kohpymc.warning_filters import pymc_info_hidden, warn_user

__all__ = [
    "MultiOutputCalibration",
    "calibrate_outputs",
    "predict_output",
    "stacked_taylor_check",
]


@dataclass
class MultiOutputCalibration:
    """A joint calibration of several outputs: set-up, built model, posterior.

    Attributes
    ----------
    physics : MultiOutputPhysics
    data : MultiOutputData
    discrepancy : Any
        What was given (a formulation, a mapping per output, a ``Coregionalized``).
    built : MultiOutputModel
    idata : arviz.InferenceData
        ``posterior`` (θ shared, per-output variables prefixed ``<k>::``),
        ``sample_stats``, ``log_likelihood`` (``<k>::y`` over ``obs_<k>``),
        ``observed_data``; each ``obs_<k>`` carries the input values as coordinates
        ``<k>::<input>`` (one name per output: the outputs' rows differ).
    problems : list of str
    identifiability : IdentifiabilityReport or None
    noise_sd_prior : Any
    """

    physics: MultiOutputPhysics
    data: MultiOutputData
    discrepancy: Any
    built: MultiOutputModel
    idata: az.InferenceData
    problems: list[str] = field(default_factory=list)
    identifiability: IdentifiabilityReport | None = None
    noise_sd_prior: Any = None

    @property
    def outputs(self) -> tuple[str, ...]:
        """Calibrated outputs."""
        return self.data.outputs

    @property
    def posterior(self):
        """``idata.posterior``."""
        return self.idata.posterior

    def sigma_obs_draws(self, output: str):
        """Posterior draws of σ_obs of an output (DataArray), or ``None`` when known."""
        name = variable(output, "sigma_obs")
        return self.posterior[name] if name in self.posterior else None

    def predict(
        self, output: str, new_inputs: Any, *, random_seed: int | None = None
    ) -> az.InferenceData:
        """Predictions of one output: see :func:`predict_output`."""
        return predict_output(self, output, new_inputs, random_seed=random_seed)


def stacked_taylor_check(
    built: MultiOutputModel,
    *,
    point: Mapping[str, Any] | None = None,
    rtol: float = RTOL,
) -> IdentifiabilityReport:
    r"""The Taylor check (paper Eqs. 15–16) over the stacked, noise-scaled sensitivities.

    Row block ``k`` of the sensitivity matrix is ``∂μ_k/∂ψ / s_k``, with ``μ_k`` the mean
    of output ``k`` (physics plus discrepancy mean), ψ the shared θ and every output's
    discrepancy-mean parameters, and ``s_k`` the output's known σ_obs (else the sd of
    its data), so that outputs in different units weigh as their measurements do:

    .. math::

        A = \begin{bmatrix} \partial \mu_1/\partial\psi \,/\, s_1 \\ \vdots \\
            \partial \mu_K/\partial\psi \,/\, s_K \end{bmatrix}.

    A parameter no single output identifies can be identified jointly (rank of the
    stack); build ``built`` with ``marginalize=False`` so the mean coefficients are
    parameters of the model.

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> from kohpymc.multi_output.model import compose_multi_output_model
    >>> built = compose_multi_output_model(bm.physics_model(), bm.generate_data(),
    ...                                    bm.formulations(), marginalize=False)
    >>> report = stacked_taylor_check(built)
    >>> report.identifiable
    True
    >>> report.names  # doctest: +NORMALIZE_WHITESPACE
    ['E', 'u::delta_mean[1]', 'u::delta_mean[x]', 'u::delta_mean[P]', 'u::delta_mean[x*P]',
     'strain::delta']
    """
    import pytensor.graph as pg
    import pytensor.tensor as pt

    if built.joint is not None:
        means = [built.joint.mean / built.joint.noise_scale]
    else:
        means = [part.mean / part.noise_scale for part in built.parts.values()]
    mu = pt.concatenate([pt.flatten(m) for m in means])
    model = built.model
    start = model.initial_point()
    values = _design_point(model, point, start)
    upstream = set(pg.ancestors([mu]))
    rvs = [rv for rv in model.free_RVs if rv in upstream]
    entries = _free_names(model, rvs, start)
    values, mu_val, A = mean_and_jacobian(model, mu, rvs, values, default=point is None)
    if not np.all(np.isfinite(mu_val)):
        raise ValueError("the stacked model mean is non-finite at the expansion point")
    if A.shape[0] < A.shape[1]:
        raise ValueError(
            f"{A.shape[0]} rows over all outputs for {A.shape[1]} mean parameters: the "
            "rank check needs at least as many rows as parameters"
        )
    flat = {
        label: float(values[rv.name] if k is None else values[rv.name].reshape(-1)[k])
        for rv, label, k in entries
    }
    return analyse_matrix(A, [e[1] for e in entries], rtol=rtol, point=flat)


def _identifiability(plain: MultiOutputModel, physics: MultiOutputPhysics):
    try:
        report = stacked_taylor_check(plain)
    except ValueError as err:
        warn_user(f"identifiability check skipped: {err}", IdentifiabilityWarning)
        return None
    if not report.identifiable:
        warn_user(
            f"the joint model of outputs {list(plain.outputs)} of {physics.name!r} is not "
            f"identifiable at the prior centre (rank {report.rank} of {len(report.names)}): "
            + "; ".join(report.confounded()),
            IdentifiabilityWarning,
        )
    return report


def _variance_pairs(built: MultiOutputModel) -> list[tuple[str, str, str]]:
    """Each output's σ_obs with its formulation's variance partner, when both are free."""
    pairs = []
    for name, part in built.parts.items():
        partner = None if part.formulation is None else part.formulation.noise_partner()
        sigma = variable(name, "sigma_obs")
        if partner is not None and sigma in built.model.named_vars:
            pairs.append((sigma, variable(name, partner[0]), partner[1]))
    return pairs


@one_blas_thread()
def calibrate_outputs(
    physics: MultiOutputPhysics,
    data: MultiOutputData,
    discrepancy: Any = None,
    *,
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 4,
    cores: int | None = None,
    target_accept: float | None = None,
    random_seed: int | None = None,
    sampler: Literal["nutpie", "pymc", "smc"] | None = None,
    reparameterize: bool = True,
    mode: Literal["NUMBA", "FAST_RUN"] | None = None,
    progressbar: bool = False,
    noise_sd_prior: Any = None,
    warn: bool = True,
    check_identifiability: bool = True,
    **sample_kwargs: Any,
) -> MultiOutputCalibration:
    """Calibrate θ from every output of ``data`` jointly.

    The joint likelihood is the product of the outputs' likelihoods, each with its own
    σ_obs,k and discrepancy (see
    :func:`~kohpymc.multi_output.model.compose_multi_output_model`).

    Parameters
    ----------
    physics : MultiOutputPhysics
    data : MultiOutputData
        Calibrate on its outputs (``data.select(["u"])`` for one output alone).
    discrepancy : Discrepancy, mapping output -> Discrepancy, or Coregionalized
        Default: none (M0) for every output.
    draws, tune, chains, cores, target_accept, random_seed, sampler, reparameterize,
    mode, progressbar, warn, **sample_kwargs :
        As for :func:`kohpymc.calibrate`.
    noise_sd_prior : Prior or mapping output -> Prior, optional
        Prior of σ_obs,k for outputs without a known noise sd.
    check_identifiability : bool
        Run :func:`stacked_taylor_check` at the prior centre first (warns on a deficit).

    Returns
    -------
    MultiOutputCalibration

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> cal = calibrate_outputs(bm.physics_model(), bm.generate_data(seed=1),
    ...                         bm.formulations(), draws=300, tune=300, chains=2,
    ...                         random_seed=1)  # doctest: +SKIP
    >>> cal.posterior["E"].dims  # doctest: +SKIP
    ('chain', 'draw')
    """
    chosen = resolve_sampler(sampler, None, None)
    check_compile_mode(mode)
    built, report = _composed(physics, data, discrepancy, noise_sd_prior, check_identifiability)
    if target_accept is None:
        target_accept = _default_target_accept(built, discrepancy)
    idata, sampling = sample_posterior(
        built.model,
        sampler=chosen,
        draws=draws,
        tune=tune,
        chains=chains,
        cores=cores,
        target_accept=target_accept,
        random_seed=random_seed,
        progressbar=progressbar,
        reparameterize=reparameterize,
        mode=mode,
        sample_kwargs=sample_kwargs,
        variance_pairs=_variance_pairs(built),
    )
    problems = _annotate(idata, built, physics, data, sampling)
    if problems and warn:
        _warn_problems(data, problems)
    outputs_problems = _outputs_physics_problems(physics, data, idata, warn)
    idata.attrs[PHYSICS_PROBLEMS] = json.dumps(outputs_problems)
    return MultiOutputCalibration(
        physics, data, discrepancy, built, idata, problems, report, noise_sd_prior
    )


def _composed(
    physics: MultiOutputPhysics,
    data: MultiOutputData,
    discrepancy: Any,
    noise_sd_prior: Any,
    check_identifiability: bool,
) -> tuple[MultiOutputModel, Any]:
    """The joint model, and the identifiability report of its unmarginalised twin (or None)."""
    built = compose_multi_output_model(physics, data, discrepancy, noise_sd_prior=noise_sd_prior)
    report = None
    if check_identifiability:
        plain = compose_multi_output_model(
            physics, data, discrepancy, noise_sd_prior=noise_sd_prior, marginalize=False
        )
        report = _identifiability(plain, physics)
    return built, report


def _default_target_accept(built: MultiOutputModel, discrepancy: Any) -> float:
    """The highest default target acceptance of the outputs' formulations."""
    accepts = [p.formulation.default_target_accept for p in built.parts.values()
               if p.formulation is not None]  # fmt: skip
    return max(accepts, default=getattr(discrepancy, "default_target_accept", 0.9))


def _outputs_physics_problems(
    physics: MultiOutputPhysics, data: MultiOutputData, idata: az.InferenceData, warn: bool
) -> list[str]:
    """Every output's :meth:`~kohpymc.PhysicsModel.posterior_problems` at the joint mean.

    An emulated output is scored against the simulator at the posterior mean of θ on its
    own calibration rows; its problems are named by output.
    """
    mean, sd = posterior_moments(idata, list(physics.parameter_names))
    return [
        f"{name}: {problem}"
        for name in data.outputs
        for problem in problems_at_posterior(
            physics.output(name), data[name], mean, sd, label="the joint posterior", warn=warn
        )
    ]


def _warn_problems(data: MultiOutputData, problems: list[str]) -> None:
    """Warn of the sampler's problems, attributed to the caller of :func:`calibrate_outputs`."""
    warn_user(
        f"joint calibration of {list(data.outputs)}: " + "; ".join(problems),
        SamplerTroubleWarning,
    )


def _annotate(
    idata: az.InferenceData,
    built: MultiOutputModel,
    physics: MultiOutputPhysics,
    data: MultiOutputData,
    sampling: SamplingReport,
) -> list[str]:
    """Add log-likelihoods, input coordinates and attributes to ``idata``; return problems."""
    idata.add_groups(log_likelihood=compute_log_likelihood(idata, built.model))
    add_pointwise_log_likelihood(idata, built)  # LOO conditionals where rows are dependent
    for name in data.outputs:  # every output's rows: coordinates <output>::<input>
        coords = {variable(name, k): v for k, v in data[name].inputs.items()}
        _attach_input_coords(idata, obs_dim(name), coords)
    problems = run_problems(idata, sampling.second_run)
    problems += list(sampling.reparameterization.get("warnings", []))
    idata.attrs.update(
        {
            "outputs": json.dumps(list(data.outputs)),
            "physics": physics.name,
            "noise_sd": json.dumps(data.noise_sd),
            "sampler": sampling.sampler,
            "sampling": json.dumps(sampling.to_dict()),
            "wall_time_s": sum(sampling.timings.values()),
        }
    )
    return problems


@one_blas_thread()
def predict_output(
    calibration: MultiOutputCalibration,
    output: str,
    new_inputs: Any,
    *,
    random_seed: int | None = None,
) -> az.InferenceData:
    """Posterior predictions of one output at new inputs (paper Eq. 20, per output).

    Returns
    -------
    arviz.InferenceData
        A ``predictions`` group with ``physics``, ``discrepancy``, ``y_model`` and
        ``y_pred`` (the output's prefix removed), dims ``(chain, draw, pred)``;
        ``pred`` carries the input values as coordinates and ``attrs["output"]`` names
        the output.

    Examples
    --------
    >>> pred = predict_output(cal, "strain", {"x": [0.0], "P": [8.0]})  # doctest: +SKIP
    >>> pred.predictions["y_model"].dims  # doctest: +SKIP
    ('chain', 'draw', 'pred')
    """
    if output not in calibration.outputs:
        raise KeyError(f"no output {output!r}; calibrated outputs are {list(calibration.outputs)}")
    built = compose_multi_output_model(
        calibration.physics,
        calibration.data,
        calibration.discrepancy,
        noise_sd_prior=calibration.noise_sd_prior,
        new_inputs={output: new_inputs},
    )
    names = built.parts[output].input_names
    Xn = new_input_matrix(new_inputs, names)
    wanted = ["physics", "discrepancy", "y_model", "y_pred"]
    with pymc_info_hidden():
        requested = [variable(output, k) for k in wanted]
        pred = sample_predictions(calibration.idata, built.model, requested, random_seed)
    renamed = pred.predictions.rename(dict(zip(requested, wanted, strict=True)))  # type: ignore[attr-defined]  # arviz adds groups at run time
    pred.predictions = renamed  # type: ignore[attr-defined]
    _attach_input_coords(pred, PRED_DIM, {k: Xn[:, j] for j, k in enumerate(names)})
    pred.attrs["output"] = output
    return pred
