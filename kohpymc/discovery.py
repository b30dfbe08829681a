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

from kohpymc.checks import check_physics_runs, check_validation_data
from kohpymc.identifiability import analyse_matrix
from kohpymc.validation import fit_and_score

__all__ = [
    "TermSelection",
    "select_terms",
    "DiscoveryReport",
    "augmented_physics",
    "disagreement_regions",
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
        Whether a missing effect was found (posterior probability of "nothing missing"
        below ``threshold``).
    effect : str or None
        The added term(s), e.g. ``"c * x * P"``.
    inputs : list of str
        Inputs the added term depends on.
    where : list of dict
        Ranges of the named inputs where the model as given fails
        (``{"input", "from", "to", "data", "rows"}``, see :func:`discover`).
    validation : dict
        ``{"before": {...}, "after": {...}}`` with ``mu_r``, ``mu_r_mcse``, ``rmse``,
        ``coverage90``.
    parameters, parameters_sd : dict
        Posterior means and sds of the parameters before and after.
    selection : TermSelection
        The term comparison.
    input_probability : dict input -> float
        Posterior probability that the missing effect depends on each input.
    threshold : float
        The significance threshold used.
    physics : PhysicsModel
        The augmented model (the original one when nothing is missing).
    before, after : InferenceData
        Calibrations with predictions at the validation inputs.
    key_input : str
        The input along which the added term (before: the squared residual) varies most
        (largest first-order variance share), for plotting.
    residuals : dict
        ``{"before": array, "after": array}``: calibration residuals from the
        posterior-mean model.
    """

    significant: bool
    effect: str | None
    inputs: list[str]
    where: list[dict]
    validation: dict
    parameters: dict
    parameters_sd: dict
    selection: TermSelection
    input_probability: dict
    threshold: float
    physics: Any
    before: Any
    after: Any
    key_input: str
    residuals: dict

    def to_dict(self) -> dict:
        """The JSON report.

        Examples
        --------
        >>> sel = TermSelection((), 0.9, {}, [((), 0.9)])
        >>> r = DiscoveryReport(False, None, [], [], {}, {}, {}, sel, {}, 0.01, None,
        ...                     None, None, "x", {})
        >>> r.to_dict()["significant"], r.to_dict()["effect"]
        (False, None)
        """
        return {
            "significant": self.significant,
            "effect": self.effect,
            "inputs": list(self.inputs),
            "where": self.where,
            "validation": self.validation,
            "parameters": self.parameters,
            "parameters_sd": self.parameters_sd,
            "criterion": {
                "probability_nothing_missing": self.selection.probability_none,
                "threshold": self.threshold,
            },
            "input_probability": self.input_probability,
            "rejected_candidates": self.selection.rejected,
            "top_subsets": [
                {"terms": list(s), "probability": p} for s, p in self.selection.subsets[:5]
            ],
        }


def augmented_physics(physics, terms, coefficient_sd: Sequence[float]):
    """``G(x; θ) + Σ_k c_k φ_k(x)`` as a new :class:`~kohpymc.PhysicsModel`.

    The coefficients are parameters ``c_<k>`` with ``Normal(0, coefficient_sd[k])`` priors.
    A decaying exponential ``exp(-x / s)`` (a term with ``decay_scale``) gets its scale as
    a parameter ``tau_<k>`` too, with a ``LogNormal(log s, 0.7)`` prior (a factor 2 either
    way within one sd).  The physics function is called with its own inputs and
    parameters only; a user Jacobian of ``physics`` is extended with the term columns.

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
    from kohpymc.priors import LogNormal, Normal

    if physics.backend != "numpy":
        raise NotImplementedError("augmenting a pytensor-backend physics model is not supported")
    coefs = [f"c_{k + 1}" for k in range(len(terms))]
    taus = {
        k: f"tau_{k + 1}" for k, t in enumerate(terms) if getattr(t, "decay_scale", None)
    }  # fmt: skip
    clash = (set(coefs) | set(taus.values())) & set(physics.parameters)
    if clash:
        raise ValueError(f"augmented model: parameter name(s) {sorted(clash)} already used")
    original = physics.function
    own = list(physics.parameters)
    inputs = list(dict.fromkeys(list(physics.inputs) + [i for t in terms for i in t.inputs]))

    def column(k, t, x, params):
        if k in taus:
            return np.exp(-np.asarray(x[t.inputs[0]], dtype=float) / params[taus[k]])
        return t(x)

    def function(x, params):
        base = original({k: x[k] for k in physics.inputs}, {k: params[k] for k in own})
        extra = sum(
            params[c] * column(k, t, x, params)
            for k, (c, t) in enumerate(zip(coefs, terms, strict=True))
        )
        return base + extra

    jacobian = None
    if physics.jacobian is not None:
        user = physics.jacobian

        def jacobian(x, params):
            J = user({k: x[k] for k in physics.inputs}, {k: params[k] for k in own})
            if isinstance(J, dict):
                J = np.column_stack([np.asarray(J[p], dtype=float) for p in physics.parameters])
            cols = [np.asarray(J, dtype=float).reshape(-1, len(own))]
            cols += [column(k, t, x, params) for k, t in enumerate(terms)]
            for k, tau in taus.items():  # d/dτ c exp(-x/τ) = c x / τ² exp(-x/τ)
                xk = np.asarray(x[terms[k].inputs[0]], dtype=float)
                cols.append(params[coefs[k]] * xk / params[tau] ** 2 * np.exp(-xk / params[tau]))
            return np.column_stack(cols)

    params = dict(physics.parameters)
    params.update({c: Normal(0.0, float(s)) for c, s in zip(coefs, coefficient_sd, strict=True)})
    params.update(
        {tau: LogNormal(float(np.log(terms[k].decay_scale)), 0.7) for k, tau in taus.items()}
    )
    return PhysicsModel(
        function,
        params,
        inputs,
        jacobian=jacobian,
        fd_scheme=physics.fd_scheme,
        name=f"{physics.name} + "
        + " + ".join(
            _named(c, t, taus.get(k)) for k, (c, t) in enumerate(zip(coefs, terms, strict=True))
        ),
    )


def _named(coefficient: str, term, tau: str | None = None) -> str:
    """``"c_1 * x * P"``: the term's expression with its coefficient's (and scale's) name."""
    text = term.expression.replace("c *", f"{coefficient} *", 1)
    if tau is not None:
        text = f"{coefficient} * exp(-{term.inputs[0]}/{tau})"
    return text


def disagreement_regions(
    values: np.ndarray,
    flagged: Any,
    *,
    input_name: str,
    source: str,
    max_bins: int = 8,
    min_rows: int = 3,
) -> list[dict]:
    """Ranges of one input where the model disagrees with the data.

    The rows are sorted by ``values`` and cut into at most ``max_bins`` bins of equal
    row count (at least ``min_rows`` each, rows with equal values kept together);
    ``flagged(rows)`` decides per bin (an index array) whether the model fails there.
    Adjacent failing bins are merged into one range.

    Parameters
    ----------
    values : array (n,)
        The input's value per row.
    flagged : callable index array -> bool
        The per-bin criterion (see :func:`discover`).
    input_name, source : str
        Copied into each range (``"input"``, ``"data"``).
    max_bins, min_rows : int
        Binning.

    Returns
    -------
    list of dict
        ``{"input", "from", "to", "data", "rows"}`` per failing range.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.arange(12.0)
    >>> z = np.where(x >= 9, 5.0, 0.0)
    >>> disagreement_regions(x, lambda rows: bool(np.mean(z[rows] ** 2) > 4),
    ...                      input_name="x", source="calibration", max_bins=4)
    [{'input': 'x', 'from': 9.0, 'to': 11.0, 'data': 'calibration', 'rows': 3}]
    """
    values = np.asarray(values, dtype=float)
    order = np.argsort(values, kind="stable")
    n = values.size
    n_bins = int(max(1, min(max_bins, n // max(min_rows, 1))))
    cuts = [0]
    for b in range(1, n_bins):
        c = int(round(b * n / n_bins))
        while 0 < c < n and values[order[c]] == values[order[c - 1]]:
            c += 1  # keep equal values in one bin
        if c - cuts[-1] >= min_rows and n - c >= min_rows:
            cuts.append(c)
    cuts.append(n)
    bins = [order[a:b] for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]
    out: list[dict] = []
    previous = False
    for rows in bins:
        fails = bool(flagged(rows))
        if fails:
            lo, hi = float(values[rows].min()), float(values[rows].max())
            if previous:  # extend the running range
                out[-1]["to"] = hi
                out[-1]["rows"] += int(rows.size)
            else:
                out.append(
                    {"input": input_name, "from": lo, "to": hi, "data": source,
                     "rows": int(rows.size)}
                )  # fmt: skip
        previous = fails
    return out


def _main_effect_share(values: np.ndarray, f: np.ndarray, max_bins: int = 8) -> float:
    """Share of the variance of ``f`` explained by bins of one input (first-order index)."""
    total = float(np.var(f))
    if total == 0 or np.ptp(values) == 0:
        return 0.0
    order = np.argsort(values, kind="stable")
    parts = np.array_split(order, min(max_bins, values.size))
    means = np.array([f[p].mean() for p in parts if p.size])
    sizes = np.array([p.size for p in parts if p.size])
    return float(np.sum(sizes * (means - f.mean()) ** 2) / sizes.sum() / total)


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
    params = list(physics.parameters)
    sampler = {"draws": draws, "tune": tune, "chains": chains}

    def run(model, label):
        scored = fit_and_score(
            model, calibration, validation, None, tolerance=tolerance,
            random_seed=random_seed, label=label, warn=False, **sampler,
        )  # fmt: skip
        return scored.combined_idata(), scored.scores, scored.constant

    say("calibrating the model as given ...")
    before, scores_before, const_before = run(physics, "as given")
    theta, theta_sd_post = _moments(before, params)
    g_hat = _evaluate_or_explain(physics, calibration.inputs, theta, "calibration inputs")
    post = before.posterior
    sigma = calibration.noise_sd
    if sigma is None:
        sigma = float(post["sigma_obs"].mean()) if "sigma_obs" in post else None
    resid = calibration.y - g_hat
    z = resid / (float(np.std(resid)) if sigma is None else sigma)

    say("comparing candidate terms ...")
    J = physics.jacobian_matrix(calibration.inputs, theta)
    selection = select_terms(
        resid,
        J,
        Phi,
        [t.name for t in candidates],
        noise_sd=sigma,
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
    significant = selection.probability_none < threshold
    # the most probable non-empty subset (the overall best when something is missing, unless
    # the mass is spread so thin over many subsets that "nothing" still ranks first)
    best = next((subset for subset, _ in selection.subsets if subset), ())
    common = {
        "selection": selection,
        "input_probability": input_probability,
        "threshold": threshold,
        "before": before,
    }
    if not significant:
        say(f"nothing missing (P = {selection.probability_none:.3g} that nothing is missing)")
        share = {k: _main_effect_share(calibration.inputs[k], z**2) for k in physics.inputs}
        return DiscoveryReport(
            significant=False,
            effect=None,
            inputs=[],
            where=[],
            validation={"before": scores_before, "after": dict(scores_before)},
            parameters={"before": theta, "after": dict(theta)},
            parameters_sd={"before": theta_sd_post, "after": dict(theta_sd_post)},
            physics=physics,
            after=before,
            key_input=max(share, key=share.get),
            residuals={"before": resid, "after": resid},
            **common,
        )
    chosen = [by_name[n] for n in best]
    named_inputs = list(dict.fromkeys(i for t in chosen for i in t.inputs))
    effect = " + ".join(t.expression for t in chosen)
    say(f"missing effect: {effect} (P(nothing missing) = {selection.probability_none:.2g})")

    from scipy.stats import chi2

    rel = const_before["reliability"].values
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

    scale = max(2.0 * float(np.std(resid)), sigma or 0.0)
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
    pieces = []
    for k, t in enumerate(chosen):
        tau = f"tau_{k + 1}"
        if tau in after_mean:  # the decay scale was calibrated: report its value
            pieces.append(f"c * exp(-{t.inputs[0]}/{after_mean[tau]:.3g})")
        else:
            pieces.append(t.expression)
    effect = " + ".join(pieces)
    return DiscoveryReport(
        significant=True,
        effect=effect,
        inputs=named_inputs,
        where=where,
        validation={"before": scores_before, "after": scores_after},
        parameters={"before": theta, "after": after_mean},
        parameters_sd={"before": theta_sd_post, "after": after_sd},
        physics=augmented,
        after=after,
        key_input=max(share, key=share.get),
        residuals={"before": resid, "after": calibration.y - g_after},
        **common,
    )
