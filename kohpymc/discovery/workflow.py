"""The discovery workflow: :func:`discover`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from kohpymc.checks import check_physics_runs, check_validation_data
from kohpymc.discovery.augment import augmented_physics
from kohpymc.discovery.evidence import select_terms
from kohpymc.discovery.regions import _main_effect_share, disagreement_regions
from kohpymc.discovery.report import DiscoveryReport
from kohpymc.validation import fit_and_score

__all__ = ["discover"]


def _evaluate_or_explain(model, inputs, params, what: str) -> np.ndarray:
    """``model.evaluate`` with a clear error naming the model and the data."""
    try:
        out = np.asarray(model.evaluate(inputs, params), dtype=float)
    except Exception as err:  # noqa: BLE001 - re-raised with context
        raise ValueError(f"physics model {model.name!r} fails on the {what}: {err}") from err
    if not np.all(np.isfinite(out)):
        raise ValueError(f"physics model {model.name!r} is not finite on the {what}")
    return out


def _checked_inputs(physics, calibration, validation, tolerance, threshold, candidates, extra):
    """Check everything before any sampling; return the candidates and their design."""
    from kohpymc.candidates import candidate_library, design_matrix

    check_validation_data(physics, validation, tolerance)
    if not 0 < threshold < 1:
        raise ValueError(f"threshold must be in (0, 1), got {threshold!r}")
    if physics.backend != "numpy":
        raise NotImplementedError(
            "discovery augments the physics function; a pytensor-backend model is not supported"
        )
    needed = len(physics.parameters) + 3  # θ, one coefficient, the noise, one more row
    if calibration.n < needed:
        raise ValueError(
            f"too few data points: the calibration data has {calibration.n} rows, at least "
            f"{needed} are needed to fit {len(physics.parameters)} physics parameter(s) and "
            "any candidate term"
        )
    check_physics_runs(physics, calibration, "calibration")
    candidates = list(candidate_library(calibration.inputs, extra=extra) if candidates is None
                      else candidates)  # fmt: skip
    if not candidates:
        raise ValueError("the candidate library is empty")
    try:
        Phi = design_matrix(candidates, calibration.inputs)
    except ValueError as err:
        raise ValueError(f"candidate library on the calibration data: {err}") from err
    return candidates, Phi


def _moments(idata, names) -> tuple[dict[str, float], dict[str, float]]:
    post = idata.posterior
    return (
        {k: float(post[k].mean()) for k in names},
        {k: float(post[k].std()) for k in names},
    )


def discover(
    physics,
    calibration,
    validation,
    *,
    tolerance: float,
    candidates: Sequence[Any] | None = None,
    extra_terms: Any = None,
    max_terms: int = 2,
    threshold: float = 0.01,
    region_level: float = 0.01,
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 4,
    random_seed: int | None = None,
    progress: Any = None,
) -> DiscoveryReport:
    """Find, name and add a missing effect; show the validation gap before and after.

    1. *Where*: calibrate the physics model as given (no discrepancy); standardised
       residuals ``z = (y - G(x; θ̄)) / σ`` on the calibration data and reliability
       r(x) on the validation data (θ̄ the posterior mean).
    2. *Whether and what*: :func:`select_terms` over the candidate library built from
       every input column of the calibration data, linearised at θ̄.  **Criterion:** a
       missing effect is reported only when the posterior probability of "nothing
       missing" is below ``threshold`` (default 0.01: evidence of more than 99 : 1 at
       even prior odds, with the prior mass of "something missing" split over all
       candidate subsets, so a larger library does not raise the false-alarm rate).
       The inputs of the selected term(s) are the named inputs; ``input_probability``
       gives, for every input, the posterior probability that the missing effect
       depends on it.
    3. *Where, as ranges*: for each named input the rows are cut into up to 8 bins of
       equal count; a calibration bin fails when ``Σ z²`` exceeds its χ² quantile at
       ``region_level / 8`` (Bonferroni over the bins), a validation bin when its mean
       reliability is below 0.5.  Adjacent failing bins are merged.
    4. *Add*: the selected term(s) with coefficients ``c_k`` (normal priors scaled to
       the residual) are added (:func:`augmented_physics`) and calibrated jointly with θ.
    5. *Gap*: μ_r, RMSE and 90 % coverage on the validation data before and after.

    All inputs are checked before any sampling (empty or non-finite candidate library,
    too few rows); the augmented model is evaluated once before it is recalibrated.
    Nothing is written to disk.

    Parameters
    ----------
    physics : PhysicsModel
        The model as given (numpy backend).
    calibration, validation : CalibrationData
        Data; every input column of the calibration data is offered to the library.
    tolerance : float
        ε of the reliability metric.
    candidates : sequence of CandidateTerm, optional
        Replace the generated library.
    extra_terms : mapping, optional
        User terms added to the generated library (see
        :func:`kohpymc.candidates.candidate_library`).
    max_terms : int
        Largest number of terms added together.
    threshold : float
        Significance threshold on the probability of "nothing missing".
    region_level : float
        Family-wise level of the per-bin χ² test that marks failing ranges.
    draws, tune, chains, random_seed :
        Sampler settings of both calibrations.
    progress : callable, optional
        Called with a line of text per step.

    Returns
    -------
    DiscoveryReport

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> report = discover(beam.physics_model(), beam.generate_data((2.5, 3.0), seed=1),
    ...                   beam.generate_data((3.5,), seed=2), tolerance=0.75,
    ...                   random_seed=1)  # doctest: +SKIP
    >>> report.effect, report.inputs  # doctest: +SKIP
    ('c * x * P', ['x', 'P'])
    """
    say = progress or (lambda _m: None)
    candidates, Phi = _checked_inputs(
        physics, calibration, validation, tolerance, threshold, candidates, extra_terms
    )
    sampler = {"draws": draws, "tune": tune, "chains": chains}

    def run(model, label):
        scored = fit_and_score(
            model, calibration, validation, None, tolerance=tolerance,
            random_seed=random_seed, label=label, warn=False, **sampler,
        )  # fmt: skip
        return scored.combined_idata(), scored.scores, scored.constant

    say("calibrating the model as given ...")
    fit = _locate_residuals(physics, calibration, run)
    say("comparing candidate terms ...")
    selection, input_probability = _select(physics, calibration, candidates, Phi, fit, max_terms)
    common = {
        "selection": selection,
        "input_probability": input_probability,
        "threshold": threshold,
        "before": fit.idata,
    }
    if not selection.probability_none < threshold:
        say(f"nothing missing (P = {selection.probability_none:.3g} that nothing is missing)")
        return _nothing_missing_report(physics, calibration, fit, common)
    # the most probable non-empty subset (the overall best when something is missing, unless
    # the mass is spread so thin over many subsets that "nothing" still ranks first)
    best = next((subset for subset, _ in selection.subsets if subset), ())
    by_name = {t.name: t for t in candidates}
    chosen = [by_name[n] for n in best]
    named_inputs = list(dict.fromkeys(i for t in chosen for i in t.inputs))
    effect = " + ".join(t.expression for t in chosen)
    say(f"missing effect: {effect} (P(nothing missing) = {selection.probability_none:.2g})")
    where = _where_it_fails(calibration, validation, named_inputs, fit, region_level)
    return _augment_and_refit(
        physics, calibration, validation, chosen, named_inputs, where, fit, run, say, common
    )


@dataclass
class _AsGiven:
    """The calibration of the model as given and its residuals on the calibration data."""

    idata: Any
    scores: dict
    constant: Any
    theta: dict[str, float]
    theta_sd: dict[str, float]
    sigma: float | None
    resid: np.ndarray
    z: np.ndarray


def _locate_residuals(physics, calibration, run) -> _AsGiven:
    """Step 1: calibrate as given; residuals ``y - G(x; θ̄)`` and their standardised ``z``."""
    before, scores_before, const_before = run(physics, "as given")
    theta, theta_sd_post = _moments(before, list(physics.parameters))
    g_hat = _evaluate_or_explain(physics, calibration.inputs, theta, "calibration inputs")
    post = before.posterior
    sigma = calibration.noise_sd
    if sigma is None:
        sigma = float(post["sigma_obs"].mean()) if "sigma_obs" in post else None
    resid = calibration.y - g_hat
    z = resid / (float(np.std(resid)) if sigma is None else sigma)
    return _AsGiven(before, scores_before, const_before, theta, theta_sd_post, sigma, resid, z)


def _select(physics, calibration, candidates, Phi, fit: _AsGiven, max_terms: int):
    """Step 2: the term comparison at θ̄ and the probability that each input matters."""
    params = list(physics.parameters)
    J = physics.jacobian_matrix(calibration.inputs, fit.theta)
    selection = select_terms(
        fit.resid,
        J,
        Phi,
        [t.name for t in candidates],
        noise_sd=fit.sigma,
        parameter_sd=[float(physics.parameters[k].sd()) for k in params],
        max_terms=max_terms,
    )
    by_name = {t.name: t for t in candidates}
    all_inputs = list(dict.fromkeys(i for t in candidates for i in t.inputs))
    input_probability = {
        k: float(
            sum(p for subset, p in selection.subsets if any(k in by_name[n].inputs for n in subset))
        )
        for k in all_inputs
    }
    return selection, input_probability


def _nothing_missing_report(physics, calibration, fit: _AsGiven, common: dict) -> DiscoveryReport:
    """The report when no missing effect is significant: "after" is "before"."""
    share = {k: _main_effect_share(calibration.inputs[k], fit.z**2) for k in physics.inputs}
    return DiscoveryReport(
        significant=False,
        effect=None,
        inputs=[],
        where=[],
        validation={"before": fit.scores, "after": dict(fit.scores)},
        parameters={"before": fit.theta, "after": dict(fit.theta)},
        parameters_sd={"before": fit.theta_sd, "after": dict(fit.theta_sd)},
        physics=physics,
        after=fit.idata,
        key_input=max(share, key=share.get),
        residuals={"before": fit.resid, "after": fit.resid},
        **common,
    )


def _where_it_fails(calibration, validation, named_inputs, fit: _AsGiven, region_level: float):
    """Step 3: failing ranges of the named inputs on the calibration and validation data."""
    from scipy.stats import chi2

    z = fit.z
    rel = fit.constant["reliability"].values
    where: list[dict] = []
    for k in named_inputs:
        where += disagreement_regions(
            calibration.inputs[k],
            lambda rows: chi2.sf(float(np.sum(z[rows] ** 2)), rows.size) < region_level / 8,
            input_name=k,
            source="calibration",
        )
        where += disagreement_regions(
            validation.inputs[k],
            lambda rows: float(np.mean(rel[rows])) < 0.5,
            input_name=k,
            source="validation",
        )
    return where


def _augment_and_refit(
    physics, calibration, validation, chosen, named_inputs, where, fit: _AsGiven, run, say, common
) -> DiscoveryReport:
    """Steps 4 and 5: add the chosen term(s), check, recalibrate and report."""
    params = list(physics.parameters)
    theta = fit.theta
    scale = max(2.0 * float(np.std(fit.resid)), fit.sigma or 0.0)
    coef_sd = [scale / max(float(np.std(t(calibration.inputs))), 1e-300) for t in chosen]
    augmented = augmented_physics(physics, chosen, coef_sd)
    start = {  # θ̄, no added term, scales at their prior centre
        k: theta[k] if k in theta else (0.0 if k.startswith("c_") else prior.mean())
        for k, prior in augmented.parameters.items()
    }
    for what, data in (("calibration", calibration), ("validation", validation)):
        _evaluate_or_explain(augmented, data.inputs, start, f"{what} inputs (augmented model)")
    say(f"recalibrating {augmented.name} ...")
    after, scores_after, _ = run(augmented, "augmented")
    new_names = [c for c in augmented.parameters if c not in physics.parameters]
    after_mean, after_sd = _moments(after, params + new_names)
    g_after = _evaluate_or_explain(augmented, calibration.inputs, after_mean, "calibration inputs")
    added = g_after - physics.evaluate(calibration.inputs, {k: after_mean[k] for k in params})
    share = {k: _main_effect_share(calibration.inputs[k], added) for k in named_inputs}
    return DiscoveryReport(
        significant=True,
        effect=_effect_text(chosen, after_mean),
        inputs=named_inputs,
        where=where,
        validation={"before": fit.scores, "after": scores_after},
        parameters={"before": theta, "after": after_mean},
        parameters_sd={"before": fit.theta_sd, "after": after_sd},
        physics=augmented,
        after=after,
        key_input=max(share, key=share.get),
        residuals={"before": fit.resid, "after": calibration.y - g_after},
        **common,
    )


def _effect_text(chosen, after_mean: dict[str, float]) -> str:
    """``"c * x * P + ..."``; a calibrated decay scale is reported by its value."""
    pieces = []
    for k, t in enumerate(chosen):
        tau = f"tau_{k + 1}"
        if tau in after_mean:  # the decay scale was calibrated: report its value
            pieces.append(f"c * exp(-{t.inputs[0]}/{after_mean[tau]:.3g})")
        else:
            pieces.append(t.expression)
    return " + ".join(pieces)
