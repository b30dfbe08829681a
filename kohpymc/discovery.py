"""Discovery: which candidate term explains the disagreement between model and data.

This module holds the selection step of the discovery workflow (issue 5, in progress):
Bayesian model comparison of small sets of candidate terms (:mod:`kohpymc.candidates`)
on the residuals of a calibrated model, *linearised in the physics parameters*, so a
term that the physics parameters can mimic earns no credit.

Around the calibrated point θ̂ the residual ``r = y - G(x; θ̂)`` is modelled as::

    r = J Δθ + Φ_S c + ε,   Δθ ~ N(0, diag(s_θ²)),  c ~ N(0, s_c² I),  ε ~ N(0, σ² I)

with ``J = ∂G/∂θ`` at θ̂ and ``Φ_S`` the (unit-sd) columns of a candidate subset S.  The
evidence ``p(r | S)`` is a zero-mean normal with covariance
``σ² I + J diag(s_θ²) Jᵀ + s_c² Φ_S Φ_Sᵀ``, exact for this linear model.  Subsets up to
``max_terms`` are enumerated; the prior gives half its mass to "nothing missing" and
splits the other half equally over the subset sizes and then over the subsets of each
size, which pays for the number of candidates tried (multiplicity control).  A candidate
whose column lies in the span of ``J`` (rank check as in
:func:`kohpymc.identifiability.analyse_matrix`) is rejected with the reason before the
comparison.  With σ unknown it is set per subset to the value that maximises the
evidence (type-II maximum likelihood).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from kohpymc.identifiability import analyse_matrix

__all__ = [
    "TermSelection",
    "select_terms",
    "DiscoveryReport",
    "augmented_physics",
    "discover",
]


@dataclass
class TermSelection:
    """Result of :func:`select_terms`.

    Attributes
    ----------
    best : tuple of str
        Names of the most probable subset (empty: nothing missing).
    probability_none : float
        Posterior probability that no candidate term is needed.
    inclusion : dict name -> float
        Posterior inclusion probability of each admissible candidate.
    subsets : list of (tuple of str, float)
        Subsets with their posterior probabilities, most probable first.
    rejected : dict name -> str
        Candidates rejected before the comparison, with the reason.
    """

    best: tuple[str, ...]
    probability_none: float
    inclusion: dict[str, float]
    subsets: list[tuple[tuple[str, ...], float]]
    rejected: dict[str, str] = field(default_factory=dict)


def _log_evidence(r: np.ndarray, base: np.ndarray, Phi: np.ndarray, coef_sd: float, sd):
    """Log N(r; 0, base + σ² I + s_c² Φ Φᵀ); ``sd`` a float or None (maximised)."""
    extra = base + (coef_sd**2) * (Phi @ Phi.T) if Phi.size else base
    n = r.size

    def logpdf(log_sd: float) -> float:
        cov = extra + np.exp(2 * log_sd) * np.eye(n)
        chol = np.linalg.cholesky(cov)
        z = np.linalg.solve(chol, r)
        return float(-0.5 * z @ z - np.sum(np.log(np.diag(chol))) - 0.5 * n * np.log(2 * np.pi))

    if sd is not None:
        return logpdf(np.log(sd))
    scale = max(float(np.std(r)), 1e-12)
    res = minimize_scalar(
        lambda s: -logpdf(s), bounds=(np.log(scale) - 12, np.log(scale) + 2), method="bounded"
    )
    return -float(res.fun)


def select_terms(
    residual: np.ndarray,
    jacobian: np.ndarray,
    candidates: np.ndarray,
    names: Sequence[str],
    *,
    noise_sd: float | None,
    parameter_sd: Sequence[float],
    coefficient_sd: float | None = None,
    max_terms: int = 2,
    rtol: float = 1e-7,
) -> TermSelection:
    """Posterior over small subsets of candidate terms for the residual of a calibrated model.

    Parameters
    ----------
    residual : array (n,)
        ``y - G(x; θ̂)``.
    jacobian : array (n, p)
        ``∂G/∂θ`` at θ̂.
    candidates : array (n, k)
        Candidate columns (see :func:`kohpymc.candidates.design_matrix`).
    names : sequence of str
        Names of the candidate columns.
    noise_sd : float or None
        Measurement-noise sd; None estimates it per subset (type-II ML).
    parameter_sd : sequence of float
        Prior sd of each physics parameter around θ̂ (e.g. its prior's sd).
    coefficient_sd : float, optional
        Prior sd of each coefficient of a unit-sd candidate column; default ``2 · sd(r)``
        (at least ``noise_sd``).
    max_terms : int
        Largest subset size considered.
    rtol : float
        Relative singular-value tolerance of the identifiability check.

    Returns
    -------
    TermSelection

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> x = np.linspace(0, 1, 40)
    >>> J = np.c_[np.ones_like(x)]                      # the physics can shift the level
    >>> Phi = np.c_[x, x**2, np.ones_like(x)]           # the last one it can mimic
    >>> r = 0.5 + 2.0 * x**2 + rng.normal(0, 0.05, x.size)
    >>> sel = select_terms(r, J, Phi, ["x", "x^2", "1"], noise_sd=0.05, parameter_sd=[10.0])
    >>> sel.best, sorted(sel.rejected)
    (('x^2',), ['1'])
    """
    r = np.asarray(residual, dtype=float).reshape(-1)
    J = np.asarray(jacobian, dtype=float).reshape(r.size, -1)
    C = np.asarray(candidates, dtype=float).reshape(r.size, -1)
    names = [str(n) for n in names]
    if C.shape[1] != len(names):
        raise ValueError(f"{C.shape[1]} candidate columns but {len(names)} names")
    if C.shape[1] == 0:
        raise ValueError("no candidate terms to select from")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J)) and np.all(np.isfinite(C))):
        raise ValueError("residual, Jacobian and candidate columns must be finite")
    if max_terms < 1:
        raise ValueError("max_terms must be at least 1")
    theta_sd = np.asarray(parameter_sd, dtype=float).reshape(-1)
    if theta_sd.size != J.shape[1]:
        raise ValueError(f"{theta_sd.size} parameter sds for {J.shape[1]} Jacobian columns")
    if r.size <= J.shape[1] + 1:
        raise ValueError(
            f"too few data points ({r.size}) for {J.shape[1]} parameters and any candidate term"
        )

    rejected: dict[str, str] = {}
    admissible: list[int] = []
    for j, name in enumerate(names):
        col = C[:, j]
        if np.ptp(col) == 0 and np.all(col == 0):
            rejected[name] = "identically zero on the data"
            continue
        labels = [f"theta{i}" for i in range(J.shape[1])] + [name]
        report = analyse_matrix(np.column_stack([J, col]), labels, rtol=rtol)
        if report.rank < J.shape[1] + 1:
            rejected[name] = (
                "not identifiable together with the physics parameters (its column lies in "
                "the span of dG/dtheta)"
            )
            continue
        admissible.append(j)
    if not admissible:
        raise ValueError(
            "every candidate term was rejected: "
            + "; ".join(f"{k}: {v}" for k, v in rejected.items())
        )
    scale = np.std(C[:, admissible], axis=0)
    scale = np.where(scale > 0, scale, np.abs(C[:, admissible]).max(axis=0))
    Phi = C[:, admissible] / scale
    adm_names = [names[j] for j in admissible]
    base = (J * theta_sd**2) @ J.T
    s_c = coefficient_sd or max(2.0 * float(np.std(r)), noise_sd or 0.0)
    sizes = range(0, min(max_terms, len(adm_names)) + 1)
    log_post: list[float] = []
    subsets: list[tuple[int, ...]] = []
    for size in sizes:
        combos = list(itertools.combinations(range(len(adm_names)), size))
        prior = np.log(0.5) if size == 0 else np.log(0.5 / (len(sizes) - 1) / len(combos))
        for combo in combos:
            ev = _log_evidence(r, base, Phi[:, list(combo)], s_c, noise_sd)
            subsets.append(combo)
            log_post.append(ev + prior)
    lp = np.array(log_post)
    post = np.exp(lp - lp.max())
    post /= post.sum()
    order = np.argsort(-post, kind="stable")
    inclusion = {
        name: float(sum(p for s, p in zip(subsets, post, strict=True) if i in s))
        for i, name in enumerate(adm_names)
    }
    ranked = [(tuple(adm_names[i] for i in subsets[o]), float(post[o])) for o in order]
    return TermSelection(
        best=ranked[0][0],
        probability_none=float(post[0]),
        inclusion=inclusion,
        subsets=ranked,
        rejected=rejected,
    )


# ---------------------------------------------------------------------- the workflow


@dataclass
class DiscoveryReport:
    """What :func:`discover` found and did.

    Attributes
    ----------
    significant : bool
        Whether a missing effect was found (criterion: posterior probability of "nothing
        missing" below ``threshold``).
    effect : str or None
        The added term(s), e.g. ``"c * x * P"``.
    inputs : list of str
        Inputs the added term depends on.
    where : list of dict
        Input ranges of the calibration rows with standardised residual beyond 2 and of the
        validation rows with reliability below 0.5 (``{"input", "from", "to"}``).
    validation : dict
        ``{"before": {...}, "after": {...}}`` with ``mu_r``, ``rmse``, ``coverage90``.
    parameters : dict
        Posterior means of the physics parameters before and after.
    selection : TermSelection
        The term comparison.
    physics : PhysicsModel
        The augmented model (the original one when nothing is missing).
    before, after : InferenceData
        Calibrations with predictions at the validation inputs.
    """

    significant: bool
    effect: str | None
    inputs: list[str]
    where: list[dict]
    validation: dict
    parameters: dict
    selection: TermSelection
    physics: Any
    before: Any
    after: Any

    def to_dict(self) -> dict:
        """The JSON report."""
        return {
            "significant": self.significant,
            "effect": self.effect,
            "inputs": list(self.inputs),
            "where": self.where,
            "validation": self.validation,
            "parameters": self.parameters,
            "probability_nothing_missing": self.selection.probability_none,
            "rejected_candidates": self.selection.rejected,
            "top_subsets": [
                {"terms": list(s), "probability": p} for s, p in self.selection.subsets[:5]
            ],
        }


def augmented_physics(physics, terms, coefficient_sd: Sequence[float]):
    """``G(x; θ) + Σ_k c_k φ_k(x)`` as a new :class:`~kohpymc.PhysicsModel`.

    The coefficients are parameters ``c_<k>`` with ``Normal(0, coefficient_sd[k])`` priors;
    a user Jacobian of ``physics`` is extended with the columns ``φ_k``.

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
    from kohpymc.priors import Normal

    if physics.backend != "numpy":
        raise NotImplementedError("augmenting a pytensor-backend physics model is not supported")
    names = [f"c_{k + 1}" for k in range(len(terms))]
    clash = set(names) & set(physics.parameters)
    if clash:
        raise ValueError(f"augmented model: parameter name(s) {sorted(clash)} already used")
    original = physics.function
    inputs = list(dict.fromkeys(list(physics.inputs) + [i for t in terms for i in t.inputs]))

    def function(x, params):
        base = original({k: x[k] for k in physics.inputs}, params)
        extra = sum(params[c] * t(x) for c, t in zip(names, terms, strict=True))
        return base + extra

    jacobian = None
    if physics.jacobian is not None:
        user = physics.jacobian

        def jacobian(x, params):
            J = user({k: x[k] for k in physics.inputs}, params)
            if isinstance(J, dict):
                J = np.column_stack([np.asarray(J[p], dtype=float) for p in physics.parameters])
            return np.column_stack([np.asarray(J, dtype=float)] + [t(x) for t in terms])

    params = dict(physics.parameters)
    params.update({c: Normal(0.0, float(s)) for c, s in zip(names, coefficient_sd, strict=True)})
    return PhysicsModel(
        function,
        params,
        inputs,
        jacobian=jacobian,
        fd_scheme=physics.fd_scheme,
        name=f"{physics.name} + "
        + " + ".join(_named(c, t) for c, t in zip(names, terms, strict=True)),
    )


def _named(coefficient: str, term) -> str:
    """``"c_1 * x * P"``: the term's expression with its coefficient's name."""
    return term.expression.replace("c *", f"{coefficient} *", 1)


def _failure_ranges(frame_inputs, mask, names, source: str) -> list[dict]:
    out = []
    if not np.any(mask):
        return out
    for k in names:
        vals = np.asarray(frame_inputs[k], dtype=float)[mask]
        out.append({"input": k, "from": float(vals.min()), "to": float(vals.max()), "data": source})
    return out


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
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 4,
    random_seed: int | None = None,
    progress: Any = None,
) -> DiscoveryReport:
    """Find, name and add a missing effect; show the validation gap before and after.

    1. *Where*: calibrate the physics model as given (no discrepancy), standardised
       residuals on the calibration data and reliability r(x) on the validation data.
    2. *What*: :func:`select_terms` over the candidate library built from every input in
       the data (physics inputs and any other recorded columns), linearised at the
       posterior mean.  The effect is significant when the posterior probability of
       "nothing missing" is below ``threshold`` (default 0.01, i.e. evidence of more
       than 99 : 1 at even prior odds).
    3. *Add*: the selected term(s) with calibrated coefficients (:func:`augmented_physics`),
       recalibrated jointly with θ.
    4. *Gap*: μ_r, RMSE and 90 % coverage on the validation data before and after.

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
    from kohpymc.calibration import calibrate, predict
    from kohpymc.candidates import candidate_library, design_matrix
    from kohpymc.study import validation_metrics

    say = progress or (lambda _m: None)
    if not np.isfinite(tolerance) or tolerance <= 0:
        raise ValueError(f"tolerance must be a positive number, got {tolerance!r}")
    sampler = {"draws": draws, "tune": tune, "chains": chains}
    params = list(physics.parameters)

    def run(model, seed_offset):
        seed = None if random_seed is None else random_seed + seed_offset
        idata = calibrate(model, calibration, None, random_seed=seed, warn=False, **sampler)
        pred = predict(idata, model, calibration, None, validation, random_seed=seed)
        noise = validation.noise_sd if validation.noise_sd is not None else calibration.noise_sd
        if noise is None and "sigma_obs" in idata.posterior:
            noise = float(idata.posterior["sigma_obs"].mean())
        scores, const = validation_metrics(pred, validation, tolerance, noise, None)
        idata.extend(pred)
        idata.add_groups(predictions_constant_data=const)
        return idata, scores, const

    say("calibrating the model as given ...")
    before, scores_before, const_before = run(physics, 0)
    theta = {k: float(before.posterior[k].mean()) for k in params}
    g_hat = physics.evaluate(calibration.inputs, theta)
    post = before.posterior
    sigma = calibration.noise_sd
    if sigma is None:
        sigma = float(post["sigma_obs"].mean()) if "sigma_obs" in post else None
    resid = calibration.y - g_hat
    z = resid / np.sqrt(np.var(resid - resid.mean()) if sigma is None else sigma**2)

    say("comparing candidate terms ...")
    if candidates is None:
        candidates = candidate_library(calibration.inputs, extra=extra_terms)
    candidates = list(candidates)
    if not candidates:
        raise ValueError("the candidate library is empty")
    Phi = design_matrix(candidates, calibration.inputs)
    J = physics.jacobian_matrix(calibration.inputs, theta)
    theta_sd = [float(physics.parameters[k].sd()) for k in params]
    selection = select_terms(
        resid,
        J,
        Phi,
        [t.name for t in candidates],
        noise_sd=sigma,
        parameter_sd=theta_sd,
        max_terms=max_terms,
    )
    significant = bool(selection.best) and selection.probability_none < threshold
    before_params = {k: theta[k] for k in params}
    if not significant:
        say(f"nothing missing (P = {selection.probability_none:.3g} that nothing is missing)")
        return DiscoveryReport(
            significant=False,
            effect=None,
            inputs=[],
            where=[],
            validation={"before": scores_before, "after": dict(scores_before)},
            parameters={"before": before_params, "after": dict(before_params)},
            selection=selection,
            physics=physics,
            before=before,
            after=before,
        )
    chosen = [t for t in candidates if t.name in selection.best]
    named_inputs = list(dict.fromkeys(i for t in chosen for i in t.inputs))
    effect = " + ".join(t.expression for t in chosen)
    say(f"missing effect: {effect} (P(nothing missing) = {selection.probability_none:.2g})")
    rel = const_before["reliability"].values
    where = _failure_ranges(calibration.inputs, np.abs(z) > 2.0, named_inputs, "calibration")
    where += _failure_ranges(validation.inputs, rel < 0.5, named_inputs, "validation")
    scale = max(2.0 * float(np.std(resid)), sigma or 0.0)
    coef_sd = [scale / max(float(np.std(t(calibration.inputs))), 1e-300) for t in chosen]
    augmented = augmented_physics(physics, chosen, coef_sd)
    say(f"recalibrating {augmented.name} ...")
    after, scores_after, _ = run(augmented, 1)
    after_params = {k: float(after.posterior[k].mean()) for k in params}
    for c in augmented.parameters:
        if c not in physics.parameters:
            after_params[c] = float(after.posterior[c].mean())
    return DiscoveryReport(
        significant=True,
        effect=effect,
        inputs=named_inputs,
        where=where,
        validation={"before": scores_before, "after": scores_after},
        parameters={"before": before_params, "after": after_params},
        selection=selection,
        physics=augmented,
        before=before,
        after=after,
    )
