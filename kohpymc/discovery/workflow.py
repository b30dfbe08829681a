"""The discovery workflow: :func:`discover`."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from kohpymc.candidates import DEFAULT_EXPONENTS
from kohpymc.checks import check_physics_runs, check_validation_data
from kohpymc.discovery.augment import augmented_physics
from kohpymc.discovery.dimensions import coefficient_unit, pi_terms, read_units
from kohpymc.discovery.drift import physics_terms
from kohpymc.discovery.fallback import ard_relevance, check_closed_form
from kohpymc.discovery.regions import _main_effect_share, disagreement_regions
from kohpymc.discovery.report import DiscoveryReport
from kohpymc.discovery.selection import select_terms
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


def _checked_inputs(physics, calibration, validation, tolerance, threshold, candidates, library):
    """Check everything before any sampling; return the candidates (not yet physics terms)."""
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
    if candidates is None:
        candidates = candidate_library(calibration.inputs, **library)
    candidates = list(candidates)
    if not candidates:
        raise ValueError("the candidate library is empty")
    try:
        design_matrix(candidates, calibration.inputs)
    except ValueError as err:
        raise ValueError(f"candidate library on the calibration data: {err}") from err
    return candidates


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
    exponents: Sequence[float] = DEFAULT_EXPONENTS,
    references: dict[str, float] | None = None,
    max_terms: int = 3,
    threshold: float = 0.01,
    null_draws: int = 299,
    gp_level: float | None = None,
    units: Mapping[str, str] | None = None,
    region_level: float = 0.01,
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 4,
    random_seed: int | None = None,
    progress: Any = None,
    joint: Any = None,
) -> DiscoveryReport:
    """Find, name and add a missing effect; show the validation gap before and after.

    1. *Where*: calibrate the physics model as given (no discrepancy); residuals
       ``y - G(x; θ̄)`` on the calibration data and reliability r(x) on the validation
       data (θ̄ the posterior mean).
    2. *Whether and what*: :func:`select_terms` over the candidate space
       (:func:`kohpymc.candidates.candidate_library` on every input column of the
       calibration data, plus :func:`kohpymc.discovery.drift.physics_terms`: "a
       parameter varies with an input", "the output scales with an input"), linearised
       at θ̄ so the physics parameters are re-fitted jointly with the terms, with the
       noise sd of the data when it is known and σ integrated out when it is not.
       **Criterion:** a missing effect is reported when the probability of "nothing
       missing" is smaller than on all but a ``threshold`` share of residuals
       simulated under the model as given (``null_draws`` of them): the false-alarm
       rate is ``threshold`` by construction (for the linearised model).
    3. *Where, as ranges*: for each named input the rows are cut into up to 8 bins of
       equal count; a calibration bin fails when ``Σ z²`` exceeds its χ² quantile at
       ``region_level / 8`` (Bonferroni over the bins), a validation bin when its mean
       reliability is below 0.5.  Adjacent failing bins are merged.
    4. *Closed form or GP* (:mod:`kohpymc.discovery.fallback`, calibration data only):
       a GP with ARD length scales fitted to the residual (type-II ML, physics
       parameters re-fitted) says which inputs matter; K-fold cross-validation inside
       the calibration data compares the held-out residual of the physics alone, the
       closed form and that GP.  When the closed form is rejected (it does not lower the
       held-out residual, or the GP predicts held-out rows ``ratio`` times better, or it
       is improbable and the GP better), or when no closed form is significant but the
       residual depends on an input at level ``gp_level`` (likelihood ratio, default
       ``threshold / 10``), the model is calibrated with a GP discrepancy
       (:class:`~kohpymc.discrepancy.GaussianProcess`, M4) over just those inputs and
       the report says ``"depends on t and m; no closed form found"``.  A closed form
       that does not lower the held-out calibration residual, with no input left for a
       GP, is not reported: "nothing missing" (the check can only remove alarms).
    5. *Add*: otherwise the terms of the most probable explanation (and the constant
       offset that comes with every explanation) with coefficients ``c_k`` (normal
       priors scaled to the residual) are added (:func:`augmented_physics`) and
       calibrated jointly with θ.
    6. *Gap*: μ_r, RMSE and 90 % coverage on the validation data (never used to select
       the terms or the inputs of the GP) before and after.

    All inputs are checked before any sampling; the augmented model is evaluated once
    before it is recalibrated.  Two MCMC calibrations in all; the search is analytic.
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
        Replace the generated candidate space (no physics terms are added then).
    extra_terms : mapping, optional
        User terms added to the generated library (see
        :func:`kohpymc.candidates.candidate_library`).
    exponents, references :
        Exponents of the monomials and reference values of shifted inputs.
    max_terms : int
        Largest number of terms in one explanation.
    threshold : float
        False-alarm rate of the closed-form decision (calibrated by simulation).
    units : mapping, optional
        Units of inputs and of the output (key ``"output"``), e.g. ``{"t": "s", "m":
        "kg", "output": "m"}`` (syntax: :mod:`kohpymc.units`): dimensionless groups of
        the inputs join the candidates (Buckingham π) and the report states the unit of
        each coefficient (:mod:`kohpymc.discovery.dimensions`).
    gp_level : float, optional
        Level of the GP route when no closed form is significant (default
        ``threshold / 10``); the false-alarm rate of ``discover`` is at most
        ``threshold + gp_level``.
    null_draws : int
        Simulated null residuals of the calibration.
    region_level : float
        Family-wise level of the per-bin χ² test that marks failing ranges.
    draws, tune, chains, random_seed :
        Sampler settings of both calibrations.
    progress : callable, optional
        Called with a line of text per step.
    joint : optional
        θ borrowed from a joint calibration of several outputs (built by
        :func:`kohpymc.multi_output.discover_outputs`, which passes it): the
        calibrations are joint ones viewed from this output, and the search re-fits θ
        from this output's residual *and* the other outputs' information.  Default
        None: θ is calibrated from ``calibration`` alone.

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
    ('c * x * P + c_0', ['x', 'P'])
    """
    say = progress or (lambda _m: None)
    library = {"exponents": exponents, "references": references, "extra": extra_terms}
    generated = candidates is None
    pool: list[Any] = _checked_inputs(
        physics, calibration, validation, tolerance, threshold, candidates, library
    )
    parsed, groups = _dimensionless_candidates(units, calibration, exponents, pool, generated)
    sampler = {"draws": draws, "tune": tune, "chains": chains}
    gp_level = threshold / 10 if gp_level is None else gp_level
    if not 0 < gp_level < 1:
        raise ValueError(f"gp_level must be in (0, 1), got {gp_level!r}")

    run = _calibrator(calibration, validation, tolerance, random_seed, sampler, joint)
    say("calibrating the model as given ...")
    fit = _locate_residuals(physics, calibration, run)
    seed = 0 if random_seed is None else int(random_seed)
    jacobian, selection = _search_terms(
        physics, calibration, fit, pool, say, generated=generated, exponents=exponents,
        max_terms=max_terms, threshold=threshold, null_draws=null_draws, seed=seed, joint=joint,
    )  # fmt: skip
    common = {
        "selection": selection,
        "input_probability": _input_probability(selection, calibration.inputs),
        "threshold": threshold,
        "before": fit.idata,
        "units": None if parsed is None else _units_summary(units, parsed, groups, selection),
        "theta": None if joint is None else joint.describe(),
    }
    return _conclude(
        physics, calibration, validation, fit, selection, jacobian, common, run, say,
        threshold=threshold, gp_level=gp_level, region_level=region_level, seed=seed,
    )  # fmt: skip


def _calibrator(calibration, validation, tolerance, random_seed, sampler, joint):
    """The calibrate-and-score step both calibrations go through (θ own or borrowed)."""

    def run(model, label, formulation=None, scored_out=None):
        if joint is not None:
            scored = joint.fit_and_score(model, label, formulation)
        else:
            scored = fit_and_score(
                model, calibration, validation, formulation, tolerance=tolerance,
                random_seed=random_seed, label=label, warn=False, **sampler,
            )  # fmt: skip
        if scored_out is not None:
            scored_out.append(scored)
        return scored.combined_idata(), scored.scores, scored.constant

    return run


def _search_terms(
    physics, calibration, fit, pool: list, say, *, generated, exponents, max_terms, threshold,
    null_draws, seed, joint,
):  # fmt: skip
    """Step 2: the Jacobian at θ̄ and :func:`select_terms` over the candidate pool."""
    if joint is not None:
        lenders = joint.lenders()
        say(f"θ from the {joint.describe()['source']}; information borrowed from "
            f"{_and(lenders) if lenders else 'no other output'}")  # fmt: skip
    if generated:
        pool += physics_terms(physics, fit.theta, calibration.inputs, exponents=exponents)
    say(f"comparing {len(pool)} candidate terms ...")
    jacobian = physics.jacobian_matrix(calibration.inputs, fit.theta)
    selection = select_terms(
        fit.resid,
        jacobian,
        pool,
        inputs=calibration.inputs,
        noise_sd=calibration.noise_sd,
        max_terms=max_terms,
        false_alarm=threshold,
        null_draws=null_draws,
        random_seed=seed,
        borrowed=None if joint is None else joint.borrowed_rows(fit.theta),
    )
    return jacobian, selection


def _dimensionless_candidates(units, calibration, exponents, pool: list, generated: bool):
    """Parsed units and the π groups added to ``pool`` (in place) when units are given."""
    parsed = None if units is None else read_units(units, list(calibration.inputs))
    groups: list[dict[str, int]] = []
    if parsed is not None and generated:
        extra, groups = pi_terms(calibration.inputs, parsed, exponents,
                                 taken={t.name for t in pool})  # fmt: skip
        pool += extra
    return parsed, groups


def _closed_form_line(selection, best: tuple[str, ...], chosen: list) -> str:
    """The chosen closed form, and the more probable one it was preferred to, if any."""
    probability = dict(selection.subsets)
    line = (f"most probable closed form: {_effect_text(chosen, selection.constant)} "
            f"(P = {probability[best]:.2g}; {_p(selection)})")  # fmt: skip
    top = next(subset for subset, _ in selection.subsets if subset)
    if top == best:
        return line
    extra = sorted(selection.inputs_of(top) - selection.inputs_of(best))
    return (f"closed form on the fewest inputs: {_effect_text(chosen, selection.constant)} "
            f"(P = {probability[best]:.2g}; {_p(selection)}); {' + '.join(top)} "
            f"(P = {probability[top]:.2g}) also uses {_and(extra)}, which the data do not "
            "tell apart (within a Bayes factor of 3)")  # fmt: skip


def _conclude(
    physics, calibration, validation, fit, selection, jacobian, common, run, say,
    *, threshold, gp_level, region_level, seed,
) -> DiscoveryReport:  # fmt: skip
    """Steps 3–4: a checked closed form, the GP fallback, or "nothing missing"."""
    if not selection.significant:
        relevance = ard_relevance(
            calibration.inputs, fit.resid, jacobian, noise_sd=calibration.noise_sd,
            level=gp_level, seed=seed,
        )  # fmt: skip
        if relevance.relevant:
            reason = (f"no closed form is significant ({_p(selection)}), but the "
                      f"residual depends on {_and(relevance.relevant)} (ARD likelihood ratio "
                      f"at level {gp_level:.2g})")  # fmt: skip
            fb = {"reason": reason, "relevance": relevance, "check": None,
                  "region_level": region_level}  # fmt: skip
            return _gp_fallback(physics, calibration, validation, fb, fit, run, say, common)
        say(f"nothing missing ({_p(selection)} under the model as given)")
        return _nothing_missing_report(physics, calibration, fit, common)
    best = selection.plainest()
    chosen = [selection.terms[n] for n in best if n != "1"]
    say(_closed_form_line(selection, best, chosen))
    closed = (np.column_stack([t(calibration.inputs) for t in chosen]) if chosen
              else np.zeros((calibration.n, 0)))  # fmt: skip
    check = check_closed_form(calibration.inputs, fit.resid, jacobian, closed,
                              dict(selection.subsets)[best], noise_sd=calibration.noise_sd,
                              level=threshold, seed=seed)  # fmt: skip
    common["closed_form_check"] = check.to_dict()
    if check.rejected:
        fb = {"reason": check.reason, "relevance": check.relevance, "check": check,
              "region_level": region_level}  # fmt: skip
        return _gp_fallback(physics, calibration, validation, fb, fit, run, say, common)
    if check.cv_rmse["closed_form"] >= check.cv_rmse["physics"] and not check.relevance.relevant:
        say(f"nothing missing: {check.reason} (K-fold inside the calibration data)")
        return _nothing_missing_report(physics, calibration, fit, common)
    named_inputs = list(dict.fromkeys(i for t in chosen for i in t.inputs))
    where = _where_it_fails(calibration, validation, named_inputs, fit, region_level)
    return _augment_and_refit(
        physics, calibration, validation, chosen, named_inputs, where, fit, run, say, common
    )


def _p(selection) -> str:
    """``"p = 0.0033"``, or ``"not calibrated"`` with ``null_draws=0``."""
    p = selection.p_value
    return "not calibrated" if p is None else f"p = {p:.3g}"


def _units_summary(given, parsed, groups, selection) -> dict:
    """Units of the data, the π groups offered and the coefficient unit of each term."""
    return {
        "given": dict(given),
        "si": {k: str(u) for k, u in parsed.items()},
        "pi_groups": groups,
        "coefficients": {name: coefficient_unit(term, given)
                         for name, term in selection.terms.items() if term is not None},
        "offset": given.get("output"),
    }  # fmt: skip


def _and(names: Sequence[str]) -> str:
    """``"t"``, ``"t and m"``, ``"t, m and H"``."""
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _gp_fallback(physics, calibration, validation, fb: dict, fit, run, say, common):
    """No closed form: calibrate with a GP discrepancy (M4) over the relevant inputs."""
    from kohpymc.calibration import predict
    from kohpymc.discrepancy import GaussianProcess

    relevance = fb["relevance"]
    inputs = list(relevance.relevant)
    effect = f"depends on {_and(inputs)}; no closed form found"
    say(f"{effect} ({fb['reason']}); calibrating with a GP discrepancy over {_and(inputs)} ...")
    formulation = GaussianProcess(inputs)
    scored: list = []
    after, scores_after, _ = run(physics, "gp fallback", formulation, scored)
    params = list(physics.parameters)
    after_mean, after_sd = _moments(after, params)
    at_cal = predict(scored[0].calibration, calibration, random_seed=0)
    fitted = at_cal["predictions"]["y_model"].mean(("chain", "draw")).to_numpy().astype(float)
    share = {k: _main_effect_share(calibration.inputs[k], fitted - fitted.mean())
             for k in inputs}  # fmt: skip
    common = dict(common)
    check = fb["check"]
    common.setdefault("closed_form_check", None if check is None else check.to_dict())
    where = _where_it_fails(calibration, validation, inputs, fit, fb["region_level"])
    return DiscoveryReport(
        significant=True,
        effect=effect,
        inputs=inputs,
        where=where,
        validation={"before": fit.scores, "after": scores_after},
        parameters={"before": fit.theta, "after": after_mean},
        parameters_sd={"before": fit.theta_sd, "after": after_sd},
        physics=physics,
        after=after,
        key_input=max(share, key=share.get),  # type: ignore[arg-type]
        residuals={"before": fit.resid, "after": calibration.y - fitted},
        fallback={
            "formulation": "gp",
            "inputs": inputs,
            "reason": fb["reason"],
            "log_ml_drop": relevance.log_ml_drop,
            "range_over_length_scale": relevance.inverse_length,
            "length_scale_over_range": dict(relevance.hyper.get("length", {})),
        },
        formulation=formulation,
        **common,
    )


def _input_probability(selection, inputs) -> dict[str, float]:
    """Posterior probability that the missing effect depends on each input."""
    out = {k: 0.0 for k in inputs}
    for subset, p in selection.subsets:
        used = {i for n in subset if n != "1" and selection.terms.get(n) is not None
                for i in selection.terms[n].inputs}  # fmt: skip
        for k in used:
            out[k] = out.get(k, 0.0) + p
    return {k: float(min(v, 1.0)) for k, v in out.items()}


@dataclass
class _AsGiven:
    """The calibration of the model as given and its residuals on the calibration data."""

    idata: Any
    scores: dict
    constant: Any
    theta: dict[str, float]
    theta_sd: dict[str, float]
    resid: np.ndarray
    z: np.ndarray


def _locate_residuals(physics, calibration, run) -> _AsGiven:
    """Step 1: calibrate as given; residuals ``y - G(x; θ̄)`` and their standardised ``z``.

    ``z`` (for the failing ranges only, never for the evidence) uses the data's noise
    sd, else the posterior mean of σ.
    """
    before, scores_before, const_before = run(physics, "as given")
    theta, theta_sd_post = _moments(before, list(physics.parameters))
    g_hat = _evaluate_or_explain(physics, calibration.inputs, theta, "calibration inputs")
    post = before.posterior
    sigma = calibration.noise_sd
    if sigma is None and "sigma_obs" in post:
        sigma = float(post["sigma_obs"].mean())
    resid = calibration.y - g_hat
    z = resid / (float(np.std(resid)) if sigma is None else sigma)
    return _AsGiven(before, scores_before, const_before, theta, theta_sd_post, resid, z)


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
        key_input=max(share, key=share.get),  # type: ignore[arg-type]
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
        if k in validation.inputs:
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
    scale = 2.0 * max(float(np.std(fit.resid)), float(np.abs(np.mean(fit.resid))), 1e-300)
    coef_sd = [scale / max(float(np.std(t(calibration.inputs))), 1e-300) for t in chosen]
    offset = common["selection"].constant
    augmented = augmented_physics(
        physics, chosen, coef_sd, offset_sd=scale if offset else None,
        inputs=calibration.inputs, theta=theta,
    )  # fmt: skip
    start = {k: theta.get(k, 0.0) for k in augmented.parameters}  # θ̄, no added term
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
        effect=_effect_text(chosen, offset),
        inputs=named_inputs,
        where=where,
        validation={"before": fit.scores, "after": scores_after},
        parameters={"before": theta, "after": after_mean},
        parameters_sd={"before": fit.theta_sd, "after": after_sd},
        physics=augmented,
        after=after,
        key_input=max(share, key=share.get) if share else physics.inputs[0],  # type: ignore[arg-type]
        residuals={"before": fit.resid, "after": calibration.y - g_after},
        **common,
    )


def _effect_text(chosen, offset: bool) -> str:
    """``"c * t^3/m + c_0"``; a constant offset alone is ``"c_0 (a constant offset)"``."""
    if not chosen:
        return "c_0 (a constant offset)"
    text = " + ".join(t.expression for t in chosen)
    return text + " + c_0" if offset else text
