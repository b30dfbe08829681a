"""Calibration: physics + discrepancy + data -> PyMC model -> a :class:`Calibration`.

``y_D = G(x; θ) + δ(x) + ε`` (paper Eqs. 1–2) with ``ε ~ N(0, σ_obs²)``.

* :func:`kohpymc.model.build_model` returns the PyMC model (inspect or extend it).
* :func:`calibrate` builds and samples it (NUTS, or SMC for gradient-free runs) and
  returns a :class:`Calibration`: the physics, data, formulation, built model and its
  InferenceData (``.idata``: posterior, sample_stats, log_likelihood, observed_data, the
  data's input values as coordinates of the ``obs`` dimension), with the sampler's
  problems and the identifiability report as Python objects.
* :func:`predict` (or :meth:`Calibration.predict`) draws ``y_m = G + δ``
  (``"y_model"``) and ``y_m + ε`` (``"y_pred"``) at new inputs (paper Eq. 20), plus the
  physics part (``"physics"``) and the discrepancy part (``"discrepancy"``), into a
  ``predictions`` group.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import arviz as az
import numpy as np

from kohpymc.checks import check_compile_mode, resolve_sampler
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import SamplerTroubleWarning
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.discrepancy.none import NoDiscrepancy
from kohpymc.identifiability import (
    IdentifiabilityReport,
    IdentifiabilityWarning,
    model_taylor_check,
)
from kohpymc.identifiability.model_check import regular
from kohpymc.loo import compute_log_likelihood, pointwise_log_likelihood
from kohpymc.model import OBS_DIM, PRED_DIM, CalibrationModel, compose_model, new_input_matrix
from kohpymc.physics import PhysicsModel
from kohpymc.predictive import sample_predictions
from kohpymc.presampling import SLOW_SAMPLING_S, PreSampling
from kohpymc.priors import Prior
from kohpymc.sampling import one_blas_thread, sample_posterior
from kohpymc.second_run import run_problems
from kohpymc.warning_filters import pymc_info_hidden, warn_user

__all__ = ["Calibration", "calibrate", "predict"]


def _attach_input_coords(idata: az.InferenceData, dim: str, inputs: Mapping[str, np.ndarray]):
    for group in idata.groups():
        ds = idata[group]
        if dim in ds.dims:
            extra = {k: (dim, np.asarray(v)) for k, v in inputs.items() if k not in ds.variables}
            # setattr, not idata[group] = ...: item assignment appends the group's name
            # to idata's group list again (arviz 0.23), so groups() would repeat it
            setattr(idata, group, ds.assign_coords(extra))


@dataclass
class Calibration:
    """One calibrated formulation: the set-up, the built model and its posterior.

    Attributes
    ----------
    physics : PhysicsModel
    data : CalibrationData
        The calibration data.
    formulation : Discrepancy
    built : CalibrationModel
        The sampled PyMC model with its formulation's record.
    idata : arviz.InferenceData
        ``posterior, sample_stats, log_likelihood, observed_data``; ``attrs`` hold
        plain scalars only (formulation label, physics name, method, wall time).
    problems : list of str
        Sampler trouble (r̂, divergences, ESS), empty when none.
    identifiability : IdentifiabilityReport or None
        The Taylor check at the prior centre (``None`` when skipped).
    identifiability_at_mode : IdentifiabilityReport or None
        The same check at the posterior mode found before sampling (``None`` when
        skipped or without a mode); with the mode and the sampling-time estimate in
        ``idata.attrs["presampling"]`` (:mod:`kohpymc.presampling`).
    noise_sd_prior : Prior or None
        Prior of σ_obs used (``None``: the default or a known noise sd).

    Examples
    --------
    >>> import kohpymc as kp
    >>> from kohpymc.examples import beam
    >>> cal = kp.calibrate(beam.physics_model(), beam.generate_data(seed=1),
    ...                    kp.ConstantBias(), draws=200, chains=2, random_seed=1)  # doctest: +SKIP
    >>> cal.label, cal.idata.posterior["E"].dims  # doctest: +SKIP
    ('M1', ('chain', 'draw'))
    >>> cal.predict({"x": [3.0], "P": [3.0]}).predictions["y_model"].dims  # doctest: +SKIP
    ('chain', 'draw', 'pred')
    """

    physics: PhysicsModel
    data: CalibrationData
    formulation: Discrepancy
    built: CalibrationModel
    idata: az.InferenceData
    problems: list[str] = field(default_factory=list)
    identifiability: IdentifiabilityReport | None = None
    noise_sd_prior: Prior | dict[str, Any] | None = None
    identifiability_at_mode: IdentifiabilityReport | None = None

    @property
    def label(self) -> str:
        """The formulation's label (``"M0"`` ... )."""
        return self.formulation.label

    @property
    def model(self):
        """The sampled ``pm.Model``."""
        return self.built.model

    @property
    def posterior(self):
        """``idata.posterior``."""
        return self.idata.posterior

    def predict(
        self, new_inputs: Any, *, random_seed: int | None = None, progressbar: bool = False
    ) -> az.InferenceData:
        """Posterior predictions at new inputs: see :func:`predict`."""
        return predict(self, new_inputs, random_seed=random_seed, progressbar=progressbar)

    def provenance(self) -> dict[str, Any]:
        """Attributes for a file: this calibration's set-up and results as plain values.

        Lists and reports are JSON strings here (NetCDF attributes hold scalars).
        """
        out: dict[str, Any] = dict(self.idata.attrs)
        out["discrepancy"] = json.dumps(_plain_or_repr(self.formulation))
        out["physics_parameters"] = json.dumps(list(self.physics.parameters))
        out["inputs"] = json.dumps(list(self.built.input_names))
        out["sampler_problems"] = json.dumps(self.problems)
        if self.identifiability is not None:
            out["identifiability"] = json.dumps(self.identifiability.to_dict())
        return out

    def to_netcdf(self, path: Any, idata: az.InferenceData | None = None) -> Any:
        """Write the InferenceData with :meth:`provenance` as its attributes.

        ``idata`` (default :attr:`idata`) may be an extended copy, e.g. with predictions
        and validation groups; its own attributes are kept on top of the provenance.
        """
        idata = self.idata if idata is None else idata
        copy = idata.copy()
        copy.attrs = {**self.provenance(), **idata.attrs}
        return copy.to_netcdf(str(path))


def _plain_or_repr(formulation: Discrepancy) -> Any:
    try:
        return formulation.to_dict()
    except TypeError:
        return repr(formulation)


def _identifiability(plain: CalibrationModel, physics: PhysicsModel, data: CalibrationData):
    """The Taylor check at the prior centre, warning on a rank deficit."""
    label = plain.formulation.label
    try:
        report = model_taylor_check(plain, fallback=regular(physics, data))
    except ValueError as err:
        warn_user(f"identifiability check skipped: {err}", IdentifiabilityWarning)
        return None
    if not report.identifiable:
        warn_user(
            f"{label} with {physics.name!r} is not identifiable at the prior centre "
            f"(rank {report.rank} of {len(report.names)}): "
            + "; ".join(report.confounded())
            + " (pass check_identifiability=False to skip this check)",
            IdentifiabilityWarning,
        )
    return report


def _sampler_name(sampler, method, nuts_sampler) -> str | None:
    """``sampler`` from it or its older spellings ``method`` / ``nuts_sampler``."""
    return resolve_sampler(sampler, method, nuts_sampler)


def _add_log_likelihood(idata: az.InferenceData, built, plain) -> None:
    """The ``log_likelihood`` group: the sampled model's, made pointwise where needed.

    The sampled model's own (joint) values are computed only when they are what is
    kept: rows independent in it, or no pointwise alternative.  Otherwise they would be
    replaced at once, and a dense likelihood's joint value costs a factorization per draw.
    """
    record = built.likelihood
    replaced = not record.independent_rows and (
        plain.likelihood.independent_rows
        or record.pointwise is not None
        or record.covariance is not None
    )
    if not replaced:
        idata.add_groups(log_likelihood=compute_log_likelihood(idata, built.model))
    pointwise = pointwise_log_likelihood(idata, built, plain)
    if pointwise is not None:
        idata.extend(az.InferenceData(log_likelihood=pointwise), join="right")


def _explained(problem: str, report: Any) -> str:
    """A flat-direction warning with the combinations the identifiability check names."""
    if "flat in some direction" not in problem or report is None or report.identifiable:
        return problem
    return problem + "; the identifiability check names: " + "; ".join(report.confounded())


def _variance_pairs(discrepancy: Discrepancy) -> list[tuple[str, str, str]]:
    """σ_obs with the formulation's parameter whose variance adds to σ_obs² (if any)."""
    partner = discrepancy.noise_partner()
    return [] if partner is None else [("sigma_obs", *partner)]


def _record_provenance(
    idata: az.InferenceData,
    physics: PhysicsModel,
    data: CalibrationData,
    discrepancy: Discrepancy,
    sampling: Any,
    presampling: Any,
) -> None:
    """What ran, in ``idata.attrs``: formulation, physics, noise, sampler, timings."""
    idata.attrs.update(
        {
            "formulation": discrepancy.label,
            "formulation_description": discrepancy.description,
            "physics": physics.name,
            "noise_sd": -1.0 if data.noise_sd is None else float(data.noise_sd),
            "method": "smc" if sampling.sampler == "smc" else "nuts",
            "sampler": sampling.sampler,
            "sampling": json.dumps(sampling.to_dict()),
            "reparameterization": sampling.reparameterization.get("kind", "none"),
            "compile_mode": sampling.compile_mode,
            "wall_time_s": sum(sampling.timings.values()),
            "presampling": json.dumps(presampling.to_dict()),
        }
    )


@one_blas_thread()
def calibrate(
    physics: PhysicsModel,
    data: CalibrationData,
    discrepancy: Discrepancy | None = None,
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
    noise_sd_prior: Prior | dict[str, Any] | None = None,
    warn: bool = True,
    check_identifiability: bool | Literal["at_mode"] = True,
    slow_warning_s: float | None = SLOW_SAMPLING_S,
    method: Literal["nuts", "smc"] | None = None,
    nuts_sampler: Literal["pymc", "nutpie"] | None = None,
    **sample_kwargs: Any,
) -> Calibration:
    """Calibrate a physics model under one discrepancy formulation.

    Parameters
    ----------
    physics, data, discrepancy :
        As in :func:`build_model`.
    draws, tune, chains, cores, random_seed :
        Sampler settings (``cores`` defaults to :func:`~kohpymc.sampling.default_cores`).
    sampler : {"nutpie", "pymc", "smc"}, optional
        ``"nutpie"`` (default): nutpie's NUTS on the log density compiled by PyTensor,
        in coordinates whitened at the posterior mode (see ``reparameterize``); PyMC's
        NUTS runs instead, with the reason in ``idata.attrs["sampling"]``, when nutpie
        is not installed or fails.  ``"pymc"``: :func:`pymc.sample`, started at the
        mode.  ``"smc"``: :func:`pymc.sample_smc`, which needs no gradient (for
        black-box models whose finite-difference gradient is unusable).
    reparameterize : bool
        Before sampling, find the posterior mode (multi-start L-BFGS) and sample in
        coordinates whitened by the Laplace covariance there, positive bounded
        parameters on the log scale when that makes the posterior more Gaussian
        (:mod:`kohpymc.reparameterization`).  Draws are mapped back to the user's
        parameters.  ``initvals`` (a dict in the user's units) become an extra start.
    mode : {"NUMBA", "FAST_RUN"}, optional
        PyTensor compile mode of the log density and gradient.  ``None``: NUMBA, or
        the C backend (``"FAST_RUN"``) when NUMBA cannot compile the model; the one
        that ran is ``idata.attrs["compile_mode"]``.  On the beam, NUMBA evaluates
        2–3× faster than the C backend (a GP likelihood gradient ~8× without a
        system BLAS) and compiles from empty caches in 4 s where C takes 21 s.
    target_accept : float, optional
        NUTS target acceptance; default the formulation's ``default_target_accept``
        (0.9, or 0.95 for the GP formulations), at least 0.95 when the sampling
        coordinates follow a curved ridge (:data:`kohpymc.sampling.CURVED_TARGET_ACCEPT`).
    method, nuts_sampler :
        Older spellings of ``sampler`` (``method="smc"``, ``nuts_sampler="pymc"``).
    progressbar : bool
        Show the sampler's progress bar.
    noise_sd_prior : Prior, optional
        Prior of σ_obs when the data carry no noise sd.
    warn : bool
        Issue a :class:`~kohpymc.diagnostics.SamplerTroubleWarning` on problems; they
        are in :attr:`Calibration.problems` either way.
    check_identifiability : bool or "at_mode"
        Before sampling, run the Taylor check of the physics plus discrepancy mean
        (:func:`kohpymc.identifiability.check_formulation`) at the prior centre; a rank
        deficit gives an :class:`~kohpymc.identifiability.IdentifiabilityWarning` naming
        the confounded combination.  The report is :attr:`Calibration.identifiability`.
        Once the posterior mode is found the check is repeated there
        (:attr:`Calibration.identifiability_at_mode`), warning on a rank deficit (saying
        structural or practical when a confounded set is of physics parameters only) or
        an ill-conditioned (practically non-identifiable) combination.  ``"at_mode"``:
        only the check at the mode (a caller that ran the one at the prior centre, such
        as :func:`kohpymc.run_study`); ``False``: neither.
    slow_warning_s : float or None
        Before NUTS starts, estimate the sampling time (evaluation cost at the mode ×
        leapfrog steps per draw × iterations, :mod:`kohpymc.presampling`) and issue a
        :class:`~kohpymc.presampling.SlowSamplingWarning` with the reasons when it
        exceeds this many seconds (default 600); ``None``: no estimate.  The run goes
        ahead either way; the estimate is in ``idata.attrs["presampling"]``.
    **sample_kwargs :
        Any other keyword for :func:`pymc.sample` / :func:`pymc.sample_smc`.

    Returns
    -------
    Calibration
        With ``.idata``: groups ``posterior, sample_stats, log_likelihood,
        observed_data``; the ``obs`` dimension carries the input values as coordinates.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> from kohpymc.discrepancy import ConstantBias
    >>> cal = calibrate(beam.physics_model(), beam.generate_data(seed=1), ConstantBias(),
    ...                 draws=200, tune=200, chains=2, random_seed=1)  # doctest: +SKIP
    >>> cal.idata.posterior["E"].dims  # doctest: +SKIP
    ('chain', 'draw')
    """
    chosen = _sampler_name(sampler, method, nuts_sampler)
    check_compile_mode(mode)
    discrepancy = discrepancy if discrepancy is not None else NoDiscrepancy()
    built = compose_model(physics, data, discrepancy, noise_sd_prior=noise_sd_prior)
    # the direct (unmarginalized) form serves the identifiability check and, when its rows
    # are independent, the pointwise log-likelihood
    plain = compose_model(
        physics, data, discrepancy, noise_sd_prior=noise_sd_prior, marginalize=False
    )
    at_centre = check_identifiability is True
    report = _identifiability(plain, physics, data) if at_centre else None
    presampling = PreSampling(
        plain if check_identifiability in (True, "at_mode") else None,
        physics,
        data.inputs,
        label=f"{discrepancy.label} with {physics.name!r}",
        threshold_s=slow_warning_s,
        target_accept=target_accept or discrepancy.default_target_accept,
    )
    idata, sampling = sample_posterior(
        built.model,
        sampler=chosen,
        draws=draws,
        tune=tune,
        chains=chains,
        cores=cores,
        target_accept=target_accept,
        default_target_accept=discrepancy.default_target_accept,
        random_seed=random_seed,
        progressbar=progressbar,
        reparameterize=reparameterize,
        mode=mode,
        sample_kwargs=sample_kwargs,
        variance_pairs=_variance_pairs(discrepancy),
        scale_parameters=discrepancy.scale_parameters(),
        before_sampling=presampling,
    )
    _add_log_likelihood(idata, built, plain)
    _attach_input_coords(idata, OBS_DIM, data.inputs)
    problems = run_problems(idata, sampling.second_run) + [
        _explained(text, presampling.explaining(report))
        for text in sampling.reparameterization.get("warnings", [])
    ]
    _record_provenance(idata, physics, data, discrepancy, sampling, presampling)
    idata.attrs["sampler_problems"] = json.dumps(problems)  # as the docs say, in memory too
    idata.attrs[PHYSICS_PROBLEMS] = json.dumps(_posterior_problems(physics, data, idata, warn))
    if problems and warn:
        warn_user(
            f"{discrepancy.label} calibration of {physics.name!r}: " + "; ".join(problems),
            SamplerTroubleWarning,
        )
    return Calibration(
        physics, data, discrepancy, built, idata, problems, report, noise_sd_prior,
        presampling.report,
    )  # fmt: skip


#: attribute of a calibration's InferenceData: the physics model's problems at the
#: posterior (a surrogate scored against its simulator there; JSON list of str)
PHYSICS_PROBLEMS = "physics_problems"


def physics_problems(idata: az.InferenceData) -> list[str]:
    """The physics model's problems at the posterior recorded by :func:`calibrate`.

    Examples
    --------
    >>> physics_problems(az.InferenceData())
    []
    """
    return list(json.loads(idata.attrs.get(PHYSICS_PROBLEMS, "[]")))


def _posterior_problems(
    physics: PhysicsModel, data: CalibrationData, idata: az.InferenceData, warn: bool
) -> list[str]:
    """:meth:`~kohpymc.PhysicsModel.posterior_problems` at the posterior mean of θ."""
    mean, sd = posterior_moments(idata, list(physics.parameters))
    label = f"{idata.attrs.get('formulation', 'the')}'s posterior"
    return problems_at_posterior(physics, data, mean, sd, label=label, warn=warn)


def posterior_moments(
    idata: az.InferenceData, names: list[str]
) -> tuple[dict[str, float], dict[str, float]]:
    """Posterior mean and sd of each of ``names``.

    Examples
    --------
    >>> import numpy as np
    >>> idata = az.from_dict(posterior={"E": np.array([[1.0, 3.0]])})
    >>> posterior_moments(idata, ["E"])
    ({'E': 2.0}, {'E': 1.0})
    """
    posterior = idata["posterior"]
    mean = {k: float(posterior[k].mean()) for k in names}
    return mean, {k: float(posterior[k].std()) for k in names}


def problems_at_posterior(
    physics: PhysicsModel,
    data: Any,
    mean: dict[str, float],
    sd: dict[str, float],
    *,
    label: str,
    warn: bool,
) -> list[str]:
    """``physics.posterior_problems``; a failure of the check itself is a problem too.

    The draws were sampled already: an error in the check must not lose them.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> problems_at_posterior(beam.physics_model(), None, {"E": 200.0}, {"E": 5.0},
    ...                       label="M0's posterior", warn=False)
    []
    """
    try:
        return physics.posterior_problems(data, mean, sd, label=label, warn=warn)
    except Exception as err:  # noqa: BLE001 - the draws are kept; the failure is reported
        return [f"the check of the physics at the mean of {label} failed: {err!r}"]


@one_blas_thread()
def predict(
    calibration: Calibration,
    new_inputs: Any,
    *,
    random_seed: int | None = None,
    progressbar: bool = False,
) -> az.InferenceData:
    """Posterior predictions at new inputs (paper Eq. 20).

    For the GP formulations ``y_model`` is the GP conditional at ``new_inputs`` given
    the calibration data; for M2/M3 it includes a fresh draw of the independent δ.

    Parameters
    ----------
    calibration : Calibration
        Result of :func:`calibrate`.
    new_inputs : DataFrame, mapping or CalibrationData
        Where to predict; all model inputs are needed.
    random_seed : int, optional
        Seed of the predictive draws.

    Returns
    -------
    arviz.InferenceData
        A ``predictions`` group with ``physics``, ``discrepancy``, ``y_model`` (without
        noise) and ``y_pred`` (with measurement noise), dims ``(chain, draw, pred)``;
        ``pred`` carries the input values as coordinates.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> cal = calibrate(beam.physics_model(), beam.generate_data(seed=1), draws=200,
    ...                 chains=2, random_seed=1)  # doctest: +SKIP
    >>> new = beam.generate_data(loads=(3.5,), seed=2)
    >>> pred = predict(cal, new, random_seed=3)  # doctest: +SKIP
    >>> pred.predictions["y_model"].dims  # doctest: +SKIP
    ('chain', 'draw', 'pred')
    """
    if not isinstance(calibration, Calibration):
        raise TypeError(
            f"predict takes the Calibration that kohpymc.calibrate returned, "
            f"got {type(calibration).__name__}"
        )
    built = compose_model(
        calibration.physics,
        calibration.data,
        calibration.formulation,
        new_inputs=new_inputs,
        noise_sd_prior=calibration.noise_sd_prior,
    )
    names = built.input_names
    Xn = new_input_matrix(new_inputs, names)
    with pymc_info_hidden():
        pred = sample_predictions(
            calibration.idata, built.model, ["physics", "discrepancy", "y_model", "y_pred"],
            random_seed, progressbar,
        )  # fmt: skip
    _attach_input_coords(pred, PRED_DIM, {k: Xn[:, j] for j, k in enumerate(names)})
    pred.attrs["formulation"] = calibration.label
    return pred
