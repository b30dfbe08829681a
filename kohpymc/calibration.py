"""Calibration: physics + discrepancy + data -> PyMC model -> ArviZ InferenceData.

``y_D = G(x; θ) + δ(x) + ε`` (paper Eqs. 1–2) with ``ε ~ N(0, σ_obs²)``.

* :func:`kohpymc.model.build_model` returns the PyMC model (inspect or extend it).
* :func:`calibrate` builds and samples it (NUTS, or SMC for gradient-free runs) and
  returns an InferenceData with posterior, sample_stats, log_likelihood,
  observed_data and the data's input values as coordinates of the ``obs`` dimension.
* :func:`predict` draws ``y_m = G + δ`` (``"y_model"``) and ``y_m + ε``
  (``"y_pred"``) at new inputs (paper Eq. 20), plus the physics part (``"physics"``)
  and the discrepancy part (``"discrepancy"``), into a ``predictions`` group.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Mapping
from typing import Any, Literal

import arviz as az
import numpy as np
import pymc as pm

from kohpymc.data import CalibrationData
from kohpymc.diagnostics import SamplerTroubleWarning, convergence_problems
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.discrepancy.none import NoDiscrepancy
from kohpymc.identifiability import IdentifiabilityWarning, model_taylor_check
from kohpymc.loo import loo_log_likelihood
from kohpymc.model import OBS_DIM, PRED_DIM, build_model, new_input_matrix
from kohpymc.physics import PhysicsModel
from kohpymc.priors import Prior

__all__ = ["calibrate", "predict"]

#: PyTensor compile modes :func:`calibrate` accepts for PyMC's NUTS
COMPILE_MODES = ("NUMBA", "FAST_RUN")


def _attach_input_coords(idata: az.InferenceData, dim: str, inputs: Mapping[str, np.ndarray]):
    for group in idata.groups():
        ds = idata[group]
        if dim in ds.dims:
            extra = {k: (dim, np.asarray(v)) for k, v in inputs.items() if k not in ds.variables}
            idata[group] = ds.assign_coords(extra)


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
    nuts_sampler: Literal["pymc", "nutpie", "numpyro", "blackjax"] = "pymc",
    mode: Literal["NUMBA", "FAST_RUN"] | None = None,
    method: Literal["nuts", "smc"] = "nuts",
    progressbar: bool = False,
    noise_sd_prior: Prior | dict[str, Any] | None = None,
    warn: bool = True,
    check_identifiability: bool = True,
    **sample_kwargs: Any,
) -> az.InferenceData:
    """Calibrate a physics model under one discrepancy formulation.

    Parameters
    ----------
    physics, data, discrepancy :
        As in :func:`build_model`.
    draws, tune, chains, cores, random_seed, nuts_sampler :
        Passed to :func:`pymc.sample`.
    mode : {"NUMBA", "FAST_RUN"}, optional
        PyTensor compile mode of the log density and gradient that PyMC's NUTS
        evaluates (``nuts_sampler="pymc"``; other samplers compile their own).  ``None``
        is PyTensor's default (``FAST_RUN``, the C backend).  ``"NUMBA"`` compiles the
        whole graph natively: on the beam study with the physics as a PyTensor
        expression it took 0.6–0.75× the time of the C backend once numba's on-disk
        cache (``~/.pytensor/numba``) is warm; the first compilation of a new graph is
        slower.  A physics model given as a numpy function runs in numba's Python
        object mode, which is slower than the C backend: keep the default there.
    target_accept : float, optional
        NUTS target acceptance; default the formulation's ``default_target_accept``
        (0.9, or 0.95 for the GP formulations).
    method : {"nuts", "smc"}
        ``"smc"`` uses :func:`pymc.sample_smc`, which needs no gradient (for black-box
        models whose finite-difference gradient is unusable).
    progressbar : bool
        Show the sampler's progress bar.
    noise_sd_prior : Prior, optional
        Prior of σ_obs when the data carry no noise sd.
    warn : bool
        Issue a :class:`~kohpymc.diagnostics.SamplerTroubleWarning` on problems; they
        are stored in ``idata.attrs["sampler_problems"]`` either way.
    check_identifiability : bool
        Before sampling, run the Taylor check of the physics plus discrepancy mean
        (:func:`kohpymc.identifiability.check_formulation`) at the prior centre; a rank
        deficit gives an :class:`~kohpymc.identifiability.IdentifiabilityWarning` naming
        the confounded combination.  The report is stored as JSON in
        ``idata.attrs["identifiability"]``.
    **sample_kwargs :
        Any other keyword for :func:`pymc.sample` / :func:`pymc.sample_smc`.

    Returns
    -------
    arviz.InferenceData
        Groups ``posterior, sample_stats, log_likelihood, observed_data``; the ``obs``
        dimension carries the input values as coordinates.  ``attrs`` hold the
        formulation label, wall time and sampler problems (JSON list).

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> from kohpymc.discrepancy import ConstantBias
    >>> idata = calibrate(beam.physics_model(), beam.generate_data(seed=1), ConstantBias(),
    ...                   draws=200, tune=200, chains=2, random_seed=1)  # doctest: +SKIP
    >>> idata.posterior["E"].dims  # doctest: +SKIP
    ('chain', 'draw')
    """
    if mode is not None:
        if mode not in COMPILE_MODES:
            raise ValueError(f"mode must be one of {list(COMPILE_MODES)} or None, got {mode!r}")
        if method != "nuts" or nuts_sampler != "pymc":
            raise ValueError(
                "mode applies to PyMC's own NUTS (method='nuts', nuts_sampler='pymc'), "
                f"not method={method!r}, nuts_sampler={nuts_sampler!r}"
            )
        compile_kwargs = dict(sample_kwargs.pop("compile_kwargs", None) or {})
        compile_kwargs["mode"] = mode
        sample_kwargs["compile_kwargs"] = compile_kwargs
    discrepancy = discrepancy if discrepancy is not None else NoDiscrepancy()
    model = build_model(physics, data, discrepancy, noise_sd_prior=noise_sd_prior)
    # the direct (unmarginalized) form serves the identifiability check and, for M0–M3,
    # the pointwise log-likelihood
    plain = build_model(
        physics, data, discrepancy, noise_sd_prior=noise_sd_prior, marginalize=False
    )
    identifiability = None
    if check_identifiability:
        try:
            report = model_taylor_check(plain)
        except ValueError as err:
            warnings.warn(
                f"identifiability check skipped: {err}", IdentifiabilityWarning, stacklevel=2
            )
        else:
            identifiability = json.dumps(report.to_dict())
            if not report.identifiable:
                warnings.warn(
                    f"{discrepancy.label} with {physics.name!r} is not identifiable at the "
                    f"prior centre (rank {report.rank} of {len(report.names)}): "
                    + "; ".join(report.confounded())
                    + " (pass check_identifiability=False to skip this check)",
                    IdentifiabilityWarning,
                    stacklevel=2,
                )
    start = time.perf_counter()
    with model:
        if method == "nuts":
            idata = pm.sample(
                draws=draws,
                tune=tune,
                chains=chains,
                cores=cores,
                target_accept=target_accept or discrepancy.default_target_accept,
                random_seed=random_seed,
                nuts_sampler=nuts_sampler,
                progressbar=progressbar,
                idata_kwargs={"log_likelihood": True},
                **sample_kwargs,
            )
            if "log_likelihood" not in idata.groups():
                pm.compute_log_likelihood(idata, progressbar=False)
        elif method == "smc":
            idata = pm.sample_smc(
                draws=draws,
                chains=chains,
                cores=cores,
                random_seed=random_seed,
                progressbar=progressbar,
                **sample_kwargs,
            )
            pm.compute_log_likelihood(idata, progressbar=False)
        else:
            raise ValueError(f"method must be 'nuts' or 'smc', got {method!r}")
    elapsed = time.perf_counter() - start
    if discrepancy.independent_rows and "y" in idata.log_likelihood:
        if idata.log_likelihood["y"].ndim == 2:  # marginalized: use the pointwise form
            pointwise = pm.compute_log_likelihood(
                idata, model=plain, extend_inferencedata=False, progressbar=False
            )
            idata.extend(az.InferenceData(log_likelihood=pointwise), join="right")
    elif "y" in idata.log_likelihood and idata.log_likelihood["y"].ndim == 2:
        # correlated rows (GP): exact leave-one-out conditionals as the pointwise values
        # (a formulation may supply its own, e.g. GridGP's structured one)
        loo = getattr(discrepancy, "pointwise_log_likelihood", loo_log_likelihood)
        pointwise = loo(idata.posterior, model, "y", obs_dim=OBS_DIM)
        idata.extend(az.InferenceData(log_likelihood=pointwise), join="right")
    _attach_input_coords(idata, OBS_DIM, data.inputs)
    param_names = list(physics.parameters)
    problems = convergence_problems(idata) if method == "nuts" else []
    idata.attrs.update(
        {
            "formulation": discrepancy.label,
            "formulation_description": discrepancy.description,
            "discrepancy": repr(discrepancy),
            "physics": physics.name,
            "physics_parameters": json.dumps(param_names),
            "inputs": json.dumps(list(model.kohpymc["input_names"])),  # type: ignore[attr-defined]
            "noise_sd": -1.0 if data.noise_sd is None else float(data.noise_sd),
            "method": method,
            "compile_mode": mode or "default",
            "wall_time_s": elapsed,
            "sampler_problems": json.dumps(problems),
        }
    )
    if identifiability is not None:
        idata.attrs["identifiability"] = identifiability
    if problems and warn:
        warnings.warn(
            f"{discrepancy.label} calibration of {physics.name!r}: " + "; ".join(problems),
            SamplerTroubleWarning,
            stacklevel=2,
        )
    return idata


def predict(
    idata: az.InferenceData,
    physics: PhysicsModel,
    data: CalibrationData,
    discrepancy: Discrepancy | None,
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
    idata : arviz.InferenceData
        Result of :func:`calibrate` with the same physics, data and discrepancy.
    physics, data, discrepancy :
        The calibration set-up.
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
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> idata = calibrate(physics, data, draws=200, chains=2, random_seed=1)  # doctest: +SKIP
    >>> new = beam.generate_data(loads=(3.5,), seed=2)
    >>> pred = predict(idata, physics, data, None, new, random_seed=3)  # doctest: +SKIP
    >>> pred.predictions["y_model"].dims  # doctest: +SKIP
    ('chain', 'draw', 'pred')
    """
    discrepancy = discrepancy if discrepancy is not None else NoDiscrepancy()
    model = build_model(physics, data, discrepancy, new_inputs=new_inputs)
    names = model.kohpymc["input_names"]  # type: ignore[attr-defined]
    Xn = new_input_matrix(new_inputs, names)
    with model:
        pred = pm.sample_posterior_predictive(
            idata,
            var_names=["physics", "discrepancy", "y_model", "y_pred"],
            predictions=True,
            random_seed=random_seed,
            progressbar=progressbar,
        )
    _attach_input_coords(pred, PRED_DIM, {k: Xn[:, j] for j, k in enumerate(names)})
    pred.attrs["formulation"] = discrepancy.label
    return pred
