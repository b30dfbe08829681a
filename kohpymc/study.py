"""The paper's three-step study (Sections 4–5): check, calibrate, validate, then weigh.

:func:`run_study` takes a physics model, calibration and validation data and a set of
discrepancy formulations, and

1. runs the Taylor identifiability check of every formulation before any sampling
   (:func:`kohpymc.identifiability.check_formulation`);
2. calibrates each formulation (:func:`kohpymc.calibrate`) and predicts at the
   validation inputs (:func:`kohpymc.predict`) — in this process, or as tasks on a Dask
   cluster (``workers``, ``scheduler``; :mod:`kohpymc.execution`);
3. scores each on the validation data — μ_r with its Monte-Carlo standard error
   (Eq. 22), RMSE of the posterior-mean prediction, and the fraction of validation
   points inside the 90 % predictive band (with measurement noise) — and forms the
   reliability weights (Eq. 23), the LOO stacking weights on the calibration data for
   comparison (``az.compare``), and the weighted mixture (Eq. 24) as one InferenceData.

σ of y_D in the reliability integral is the same for every formulation when one exists
apart from them (known, or pooled from replicates with Eq. 28); otherwise each formulation
scores with its own posterior draws of σ_obs, draw by draw
(:func:`kohpymc.validation.validation_noise`).  The mixture is scored point by point as
``Σ_k w_k r_k(x)`` and needs no σ of its own.

A formulation that fails (an exception while building, sampling or predicting) is
reported in the table and does not stop the others.  With ``out_dir``
(:class:`kohpymc.study_files.StudyFolder`) each formulation's ``<label>.nc`` is written
the moment it finishes and ``study.json`` records every step, so a failure in a later
step (weights, mixture, figures) or a killed process loses no finished posterior.  A
rerun into the same folder reuses every formulation whose inputs are unchanged (a
fingerprint of the physics, the priors, the data, the formulation, the sampler settings
and the kohpymc version, stored in the file) and re-predicts one whose validation data
alone changed; ``fresh=True`` recomputes all.  Then ``combined.nc``, ``table.csv``,
``table.md`` and three figures; every file is written to a temporary name first and
renamed when complete.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import closing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr

from kohpymc.calibration import PHYSICS_PROBLEMS, Calibration, physics_problems
from kohpymc.checks import check_execution, check_validation_data
from kohpymc.combination import combine_posteriors, loo_weights, reliability_weights
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import RHAT_MAX, sampler_diagnostics
from kohpymc.discrepancy import Discrepancy
from kohpymc.discrepancy.defaults import default_formulations
from kohpymc.execution import run_tasks, runs_remotely
from kohpymc.fingerprint import (
    data_fingerprint,
    digest,
    formulation_fingerprint,
    kohpymc_version,
    physics_fingerprint,
)
from kohpymc.identifiability import (
    IdentifiabilityWarning,
    check_formulation,
    fisher_information_check,
)
from kohpymc.identifiability.at_mode import ridge_text
from kohpymc.model import compose_model
from kohpymc.physics import PhysicsModel
from kohpymc.progress import LineDisplay, TaskDisplay
from kohpymc.study_files import (
    CALIBRATION_HASH,
    COMBINED,
    VALIDATION_HASH,
    StudyFolder,
    calibration_part,
    markdown_table,
    write_atomic,
    write_results,
    write_table,
)
from kohpymc.validation import (
    Scored,
    derived_seed,
    describe_noise,
    fit_and_score,
    predictive_scores,
    score_calibration,
)
from kohpymc.warning_filters import single_chain_notes_hidden, warn_user

__all__ = [
    "StudyResult",
    "StudyStepError",
    "run_study",
    "markdown_table",
    "write_atomic",
]


class StudyStepError(RuntimeError):
    """A study step after the calibrations failed; finished posteriors are on disk.

    Attributes
    ----------
    step : str
        The step that failed (``"weights and mixture"``, ``"figures"`` ...).
    result : StudyResult or None
        What finished (the calibrations, a table without weights).
    """

    def __init__(self, step: str, error: BaseException, result: StudyResult | None) -> None:
        super().__init__(f"{step} failed: {type(error).__name__}: {error}")
        self.step = step
        self.result = result


@dataclass
class StudyResult:
    """Everything a study produced.

    Attributes
    ----------
    results : dict label -> InferenceData
        Per formulation: ``posterior``, ``sample_stats``, ``log_likelihood``,
        ``observed_data``, ``predictions`` (at the validation inputs) and
        ``predictions_constant_data`` (validation measurements ``y_validation`` and the
        pointwise reliability ``reliability``).
    table : pandas.DataFrame
        One row per formulation plus ``"combined"``: validation metrics, weights,
        physics-parameter posterior mean/sd, convergence and identifiability.
    weights : dict
        Reliability weights (Eq. 23).
    loo : pandas.DataFrame or None
        ``az.compare`` table on the calibration data (stacking weights).
    combined : InferenceData or None
        The reliability-weighted mixture with its predictions.
    failures : dict label -> str
        Formulations that failed and why.
    identifiability : dict label -> dict
        Taylor-check reports.
    wall_time_s : dict label -> float
        Sampling wall time per formulation (not in the table, which is reproducible).
    files : list of Path
        Files written.
    calibrations : dict label -> Calibration
        The calibrated formulations (for :func:`kohpymc.predict` at other inputs).
    validation_noise : dict label -> dict
        σ of y_D used in each formulation's reliability integral: ``source``, ``sd``
        (the mean over draws when per draw), ``per_draw`` and a ``note``.
    reused : list of str
        Formulations taken from an earlier run's files (inputs unchanged).
    """

    results: dict[str, az.InferenceData]
    table: pd.DataFrame
    weights: dict[str, float]
    loo: pd.DataFrame | None
    combined: az.InferenceData | None
    failures: dict[str, str]
    identifiability: dict[str, dict]
    wall_time_s: dict[str, float] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    calibrations: dict[str, Calibration] = field(default_factory=dict)
    validation_noise: dict[str, dict] = field(default_factory=dict)
    reused: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """The main columns of the table as text."""
        cols = [
            c
            for c in ("mu_r", "mu_r_mcse", "rmse", "coverage90", "weight", "loo_weight")
            if c in self.table
        ]
        extra = [c for c in self.table if c.endswith("_mean") or c.endswith("_sd")]
        view = self.table[cols + extra + ["r_hat_max", "divergences", "status"]].copy()
        view["status"] = [s if len(s) <= 40 else s[:37] + "..." for s in view["status"]]
        with pd.option_context("display.width", 200, "display.max_columns", 30):
            text = view.to_string(float_format=lambda v: f"{v:.4g}")
        if "validation_noise" in self.table:
            used = self.table["validation_noise"].dropna()
            text += "\n\nσ of y_D in the reliability integral:\n" + "\n".join(
                f"  {label}: {value}" for label, value in used.items()
            )
        return text


@dataclass
class _Job:
    """What every formulation's calibration in a study shares."""

    physics: PhysicsModel
    calibration: CalibrationData
    validation: CalibrationData
    tolerance: float
    validation_weights: Sequence[float] | None
    random_seed: int | None
    settings: dict[str, Any]

    def fit(self, label: str, disc: Discrepancy) -> Scored:
        """Fit and score one formulation (runs in this process)."""
        return fit_and_score(
            self.physics,
            self.calibration,
            self.validation,
            disc,
            tolerance=self.tolerance,
            validation_weights=self.validation_weights,
            random_seed=self.random_seed,
            label=label,
            check_identifiability="at_mode",  # the prior centre's: _check_identifiability
            **self.settings,
        )

    def fit_remotely(self, label: str, disc: Discrepancy) -> tuple:
        """:meth:`fit` on a Dask worker: only picklable results travel back (no model)."""
        scored = self.fit(label, disc)
        cal = scored.calibration
        payload = (cal.idata, cal.problems, cal.identifiability, cal.noise_sd_prior)
        return payload, (scored.predictions, scored.scores, scored.constant, scored.noise)

    def calibration_hash(self, label: str, disc: Discrepancy) -> str:
        """Fingerprint of everything the formulation's posterior depends on."""
        quiet = ("progressbar", "cores")  # neither changes a draw
        return digest(
            {
                "kohpymc": kohpymc_version(),
                "physics": physics_fingerprint(self.physics),
                "data": data_fingerprint(self.calibration),
                "formulation": formulation_fingerprint(disc),
                "label": label,
                "seed": self.random_seed,
                "settings": {k: v for k, v in self.settings.items() if k not in quiet},
            }
        )

    def validation_hash(self, calibration_hash: str) -> str:
        """Fingerprint of the predictions and scores on top of the posterior's."""
        weights = None if self.validation_weights is None else list(self.validation_weights)
        return digest(
            [
                calibration_hash,
                data_fingerprint(self.validation),
                repr(float(self.tolerance)),
                weights,
            ]
        )

    def rebuild(self, disc: Discrepancy, idata: az.InferenceData, problems, report) -> Calibration:
        """A Calibration around finished draws, its model rebuilt here (building is cheap)."""
        noise_prior = self.settings.get("noise_sd_prior")
        built = compose_model(self.physics, self.calibration, disc, noise_sd_prior=noise_prior)
        return Calibration(
            self.physics, self.calibration, disc, built, idata, problems, report, noise_prior
        )


def _rebuilt(job: _Job, disc: Discrepancy, payload: tuple) -> Scored:
    """A worker's results as a Scored, with the model rebuilt here."""
    (idata, problems, report, _noise_prior), rest = payload
    return Scored(job.rebuild(disc, idata, problems, report), *rest)


#: attributes of a calibration's InferenceData as :func:`kohpymc.calibrate` sets them
_CALIBRATION_ATTRS = (
    "formulation",
    "formulation_description",
    "physics",
    "noise_sd",
    "method",
    "sampler",
    "sampling",
    "reparameterization",
    "compile_mode",
    "wall_time_s",
    PHYSICS_PROBLEMS,
)


def _from_file(job: _Job, label: str, disc: Discrepancy, idata: az.InferenceData):
    """``(scored or None, how)`` from a formulation's earlier file, when still valid.

    ``how`` is ``"reused"`` (posterior and scores unchanged), ``"rescored"`` (the
    posterior is valid but the validation data or tolerance changed: predicted and scored
    again) or the reason it cannot be used.
    """
    calibration_hash = job.calibration_hash(label, disc)
    if idata.attrs.get(CALIBRATION_HASH) != calibration_hash:
        return None, "inputs changed"
    own = calibration_part(idata)
    own.attrs.update({k: idata.attrs[k] for k in _CALIBRATION_ATTRS if k in idata.attrs})
    problems = json.loads(idata.attrs.get("sampler_problems", "[]"))
    cal = job.rebuild(disc, own, problems, None)
    needed = ("predictions", "predictions_constant_data")
    stale = idata.attrs.get(VALIDATION_HASH) != job.validation_hash(calibration_hash)
    if stale or any(g not in idata.groups() for g in needed):
        return _score(job, label, cal), "rescored"
    const = idata["predictions_constant_data"]
    noise = {k[len("noise_") :]: v for k, v in const.attrs.items() if k.startswith("noise_")}
    if "per_draw" in noise:
        noise["per_draw"] = bool(noise["per_draw"])
    scores = {k: float(idata.attrs[k]) for k in ("mu_r", "mu_r_mcse", "rmse", "coverage90")}
    predictions = az.InferenceData(predictions=idata["predictions"])
    return Scored(cal, predictions, scores, const, noise), "reused"


def _score(job: _Job, label: str, cal: Calibration) -> Scored:
    return score_calibration(
        cal,
        job.validation,
        tolerance=job.tolerance,
        validation_weights=job.validation_weights,
        random_seed=job.random_seed,
        label=label,
    )


def _check_identifiability(physics, calibration, formulations, say):
    """Taylor check of every formulation before any sampling: (reports, failures)."""
    say(f"identifiability check of {len(formulations)} formulation(s) at the prior centre")
    reports: dict[str, dict] = {}
    failures: dict[str, str] = {}
    for label, disc in formulations.items():
        try:
            report = check_formulation(physics, calibration, disc)
        except Exception as err:  # noqa: BLE001 - reported, the study goes on
            failures[label] = f"identifiability check failed: {type(err).__name__}: {err}"
            say(f"  {label}: {failures[label]}")
            continue
        reports[label] = report.to_dict()
        if report.identifiable:
            weak = report.weakly_informed()  # full rank, but a direction barely informed
            say(
                f"  {label}: identifiable (rank {report.rank} of {len(report.names)})"
                + (f", weakly: {weak}" if weak else "")
            )
        else:
            text = ridge_text(report)  # with "structural" / "practical" when known
            kind = {True: ", structurally", False: ", practically (more data would help)"}
            say(
                f"  {label}: NOT identifiable{kind.get(report.structural, '')} (rank "
                f"{report.rank}/{len(report.names)}); the confounded combinations follow in an "
                "IdentifiabilityWarning"
            )
            warn_user(
                f"{label} is not identifiable at the prior centre: {text}",
                IdentifiabilityWarning,
            )
        noise = _noise_confounding(physics, calibration, disc)
        if noise is not None:
            reports[label]["noise"] = noise
            say(f"  {label}: with unknown noise, " + "; ".join(noise["confounded"]))
    return reports, failures


def _noise_confounding(physics, calibration, disc) -> dict | None:
    """The Fisher check's report when σ_obs is calibrated next to a discrepancy variance.

    With unknown noise, M2's σ_obs and σ_δ enter the likelihood only as σ_obs² + σ_δ²
    (likewise M3's log-variance intercept): the study says so before sampling.  ``None``
    when the noise is known, the formulation has no such partner, or the check finds
    the pair resolved.
    """
    if calibration.noise_sd is not None or disc.noise_partner() is None or calibration.n > 2000:
        return None
    try:
        report = fisher_information_check(physics, calibration, disc)
    except Exception:  # noqa: BLE001 - an extra diagnosis, never a reason to stop
        return None
    confounded = [text for text in report.confounded() if "sigma_obs" in text]
    if not confounded:
        return None
    return {"kind": "fisher", "confounded": confounded}


def _calibrate_all(
    job: _Job,
    formulations: Mapping[str, Discrepancy],
    todo: list[str],
    execution: dict[str, Any],
    display: TaskDisplay,
) -> Iterator[tuple[str, Scored | None, float, str | None]]:
    """Yield ``(label, scored or None, seconds, error or None)`` as formulations finish.

    In this process, or as tasks on a Dask cluster (``execution``: ``workers``,
    ``scheduler``; :func:`kohpymc.execution.run_tasks`), whose results are rebuilt here.
    """
    remote = runs_remotely(**execution)
    task = job.fit_remotely if remote else job.fit
    items = {label: formulations[label] for label in todo}
    with closing(run_tasks(task, items, progress=display, **execution)) as outcomes:
        for outcome in outcomes:
            scored, error = outcome.value, outcome.error
            if remote and error is None:
                try:
                    scored = _rebuilt(job, items[outcome.key], scored)
                except Exception as err:  # noqa: BLE001 - reported, the study goes on
                    scored, error = None, f"rebuilding the model: {type(err).__name__}: {err}"
            yield outcome.key, scored, outcome.seconds, error


def _say_scores(say, label: str, scored: Scored, seconds: float) -> None:
    scores, problems = scored.scores, scored.calibration.problems
    say(
        f"  {label}: mu_r = {scores['mu_r']:.3f} ± {scores['mu_r_mcse']:.3f}, "
        f"RMSE {scores['rmse']:.3g}, 90% coverage {scores['coverage90']:.2f}, "
        f"{seconds:.0f} s" + (f"; sampler: {'; '.join(problems)}" if problems else "")
    )


def _mixture(results, metrics, job: _Job, seed):
    """Reliability weights (Eq. 23) and the weighted mixture (Eq. 24) with its scores.

    The mixture's reliability is ``Σ_k w_k r_k(x)`` point by point (r is linear in the
    predictive distribution), so it needs no σ of its own; RMSE and coverage come from
    the mixed draws, whose ``y_pred`` carry each formulation's own noise.
    """
    params = list(job.physics.parameters)
    positive = {k: m["mu_r"] for k, m in metrics.items()}
    weights = reliability_weights(positive) if sum(positive.values()) > 0 else {}
    if not weights:
        return weights, None, None
    combined = combine_posteriors(
        results, weights, var_names=params, predictions=results, random_seed=seed
    )
    pointwise = sum(
        w * results[k].predictions_constant_data["reliability"] for k, w in weights.items()
    )
    scores = {
        "mu_r": float(sum(w * metrics[k]["mu_r"] for k, w in weights.items())),
        "mu_r_mcse": float(
            np.sqrt(sum((w * metrics[k]["mu_r_mcse"]) ** 2 for k, w in weights.items()))
        ),
        **predictive_scores(combined, job.validation),
    }
    const = xr.Dataset({"reliability": pointwise.rename("reliability")})
    const["y_validation"] = xr.DataArray(job.validation.y, dims=("pred",))
    const.attrs.update(
        {
            "mu_r": scores["mu_r"],
            "mu_r_mcse": scores["mu_r_mcse"],
            "tolerance": float(job.tolerance),
            "noise_source": "each formulation's own (mixture of r_k(x))",
        }
    )
    combined.add_groups(predictions_constant_data=const)
    combined.attrs.update({k: float(v) for k, v in scores.items()})
    return weights, combined, scores


def _loo_comparison(results, say) -> pd.DataFrame | None:
    if len(results) < 2:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return loo_weights(results)
    except Exception as err:  # noqa: BLE001 - LOO is a side comparison
        say(f"LOO comparison skipped: {err}")
        return None


def run_study(
    physics: PhysicsModel,
    calibration: CalibrationData,
    validation: CalibrationData,
    formulations: Mapping[str, Discrepancy] | None = None,
    *,
    tolerance: float,
    validation_weights: Sequence[float] | None = None,
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 4,
    target_accept: float | None = None,
    random_seed: int | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    figures: bool = True,
    reference: Mapping[str, float] | None = None,
    progress: Callable[[str], None] | None = None,
    progressbar: bool = False,
    workers: int = 1,
    scheduler: Any = None,
    display: TaskDisplay | None = None,
    fresh: bool = False,
    **calibrate_kwargs: Any,
) -> StudyResult:
    """Check, calibrate, validate and weigh a set of discrepancy formulations.

    Runs the identifiability check, calibrations, validation metrics, weights and the
    mixture, optionally writing everything to ``out_dir`` (each formulation's file as
    soon as it is finished; a rerun into the same folder reuses unchanged ones).

    Parameters
    ----------
    physics : PhysicsModel
        The physics model with parameter priors.
    calibration, validation : CalibrationData
        Calibration and validation measurements.
    formulations : mapping label -> Discrepancy, optional
        Default :func:`kohpymc.default_formulations` over the physics inputs (M0–M4).
    tolerance : float
        ε of the reliability metric (output units), > 0.
    validation_weights : sequence of float, optional
        Weights of the validation points in μ_r (Eq. 22); default uniform.
    draws, tune, chains, target_accept :
        Sampler settings for every formulation (see :func:`kohpymc.calibrate`).
    random_seed : int, optional
        Seeds every calibration, prediction and the mixture; the same seed gives the
        same table.
    out_dir : path, optional
        Folder to write results to (created if needed).  Formulations whose file there
        has the fingerprint of this run's inputs are reused, not recomputed (a changed
        validation set or tolerance only re-predicts and re-scores them).
    figures : bool
        Write the three figures (with ``out_dir``).
    reference : mapping, optional
        Known parameter values to mark in the posterior figure (synthetic studies).
    progress : callable, optional
        Called with one line of text per step (e.g. ``print``).
    progressbar : bool
        Show PyMC's sampling progress bar.
    workers : int
        More than 1: calibrate formulations at the same time on a local Dask cluster of
        this many worker processes (:func:`kohpymc.execution.run_tasks`).  The results
        are the same as with ``workers=1`` (every formulation's seed comes from
        ``random_seed`` and its label).  With ``workers`` equal to the number of cores,
        pass ``cores=1`` so the chains of each run one after the other.
    scheduler : str or distributed.Client, optional
        Calibrate on an existing Dask cluster instead: its scheduler's address
        (``"tcp://HOST:PORT"``) or a client.  The cluster is left running.
    display : TaskDisplay, optional
        Shows each formulation queued, running (compiling, sampling), done or failed
        (:mod:`kohpymc.progress`); default plain lines through ``progress``.
    fresh : bool
        Recompute every formulation even when ``out_dir`` holds valid results.
    **calibrate_kwargs :
        Further keywords for :func:`kohpymc.calibrate`.

    Returns
    -------
    StudyResult

    Raises
    ------
    StudyStepError
        When a step after the calibrations fails (weights, mixture, writing, figures):
        every finished formulation's file and a table without weights are on disk, and
        the error's ``result`` holds what finished.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> study = run_study(beam.physics_model(), beam.generate_data(seed=1),
    ...                   beam.generate_data((3.5,), seed=2), tolerance=0.75,
    ...                   random_seed=1)  # doctest: +SKIP
    >>> study.table.loc["M1", "mu_r"]  # doctest: +SKIP
    0.53
    """
    say = progress or (lambda _msg: None)
    tolerance, formulations = _checked_study(
        physics, validation, tolerance, workers, scheduler, formulations
    )
    display = display or (LineDisplay(say) if progress else TaskDisplay())
    identifiability, failures = _check_identifiability(physics, calibration, formulations, say)
    settings = dict(draws=draws, tune=tune, chains=chains, target_accept=target_accept)
    settings.update(progressbar=progressbar, **calibrate_kwargs)
    job = _Job(
        physics, calibration, validation, tolerance, validation_weights, random_seed, settings
    )
    output = _Output(figures, reference, derived_seed(random_seed, COMBINED, 2))
    folder = StudyFolder(out_dir, fresh=fresh) if out_dir is not None else None
    reused = _reuse_finished(job, formulations, failures, folder, say)
    todo = [label for label in formulations if label not in failures and label not in reused]
    # one formulation: no cluster to start (an existing one is used as asked)
    execution = {"workers": workers if len(todo) > 1 else 1, "scheduler": scheduler}
    if todo:
        say(f"calibrating {len(todo)} formulation(s)" + _where(workers, scheduler, len(todo)))
    outcomes: dict[str, tuple[Scored | None, float, str | None]] = {}
    for label, outcome, seconds, error in _calibrate_all(
        job, formulations, todo, execution, display
    ):
        outcomes[label] = (outcome, seconds, error)
        if folder is not None:
            _save(folder, job, label, formulations[label], outcome, seconds, error)
    display.close()
    try:
        scored, wall = _collect(outcomes, reused, formulations, failures, say)
    except RuntimeError as err:
        if folder is not None:
            folder.update(status="failed", error=str(err), failures=failures)
        raise
    return _finish(job, formulations, scored, wall, failures, identifiability, folder, say, output)


def _reuse_finished(job, formulations, failures, folder, say) -> dict[str, Scored]:
    """Formulations whose earlier files in the output folder are still valid."""
    reused: dict[str, Scored] = {}
    if folder is None:
        return reused
    for label, disc in formulations.items():
        if label in failures:
            folder.record(label, status="failed", error=failures[label])
            continue
        earlier = folder.finished(label)
        scored, how = (
            (None, "no file") if earlier is None else _from_file(job, label, disc, earlier)
        )
        if scored is None:
            folder.record(label, status="queued")
            if earlier is not None:
                say(f"  {label}: recomputed ({how})")
            continue
        reused[label] = scored
        if how == "rescored":
            _save(folder, job, label, disc, scored, 0.0, None, status="rescored")
        else:
            folder.record(label, status="reused", file=f"{label}.nc", validation_noise=scored.noise)
        say(f"  {label}: {how} ({folder.formulation_file(label)})")
    return reused


def _save(folder, job, label, disc, scored, seconds, error, status="done") -> None:
    """Write a finished formulation's file at once, with its fingerprints; or its failure."""
    if error is not None or scored is None:
        folder.record(label, status="failed", error=error)
        return
    calibration_hash = job.calibration_hash(label, disc)
    idata = scored.combined_idata()
    idata.attrs[CALIBRATION_HASH] = calibration_hash
    idata.attrs[VALIDATION_HASH] = job.validation_hash(calibration_hash)
    cal = scored.calibration
    path = folder.save_formulation(label, lambda p: cal.to_netcdf(p, idata))
    folder.record(
        label,
        status=status,
        file=path.name,
        wall_time_s=round(float(seconds), 2),
        validation_noise=scored.noise,
        sampler_problems=list(cal.problems),
        physics_problems=physics_problems(cal.idata),
    )


@dataclass
class _Output:
    """What the study writes besides the results (with ``out_dir``)."""

    figures: bool
    reference: Mapping[str, float] | None
    mixture_seed: int | None


def _finish(job, formulations, scored, wall, failures, identifiability, folder, say, output):
    """Weights, mixture, table and files; a failure here keeps every finished posterior.

    Raises :class:`StudyStepError` (with what finished and a table without weights)
    after writing that table and the error to the output folder.
    """
    results = {k: s.combined_idata() for k, s in scored.items()}
    metrics = {k: dict(s.scores) for k, s in scored.items()}
    partial = StudyResult(
        results=results,
        table=pd.DataFrame(),
        weights={},
        loo=None,
        combined=None,
        failures=failures,
        identifiability=identifiability,
        wall_time_s=wall,
        calibrations={k: s.calibration for k, s in scored.items()},
        validation_noise={k: s.noise for k, s in scored.items()},
        reused=[k for k in scored if k not in wall],
    )
    step = "LOO comparison"
    try:
        loo = _loo_comparison(results, say)
        step = "weights and mixture"
        weights, combined, combined_scores = _mixture(results, metrics, job, output.mixture_seed)
        if combined_scores is not None:
            metrics[COMBINED] = combined_scores
        step = "table"
        table = _table(
            formulations, scored, results, metrics, weights, loo, failures, identifiability
        )
        result = replace(partial, table=table, weights=weights, loo=loo, combined=combined)
        if folder is not None:
            step = "writing results"
            write_results(
                result, folder, job.physics, job.validation, output.figures, output.reference
            )
            folder.update(status="complete", error=None)
            result.files = list(folder.files)
            say(f"wrote {len(result.files)} files to {folder.path}")
    except Exception as err:
        _keep_what_finished(partial, formulations, scored, metrics, folder, step, err)
        raise StudyStepError(step, err, partial) from err
    return result


def _keep_what_finished(partial, formulations, scored, metrics, folder, step, err) -> None:
    """After a failed step: a table of the finished formulations, the error in the manifest."""
    only = {k: v for k, v in metrics.items() if k != COMBINED}
    try:
        partial.table = _table(
            formulations, scored, partial.results, only, {}, None, partial.failures,
            partial.identifiability,
        )  # fmt: skip
    except Exception:  # noqa: BLE001 - the original error is the one to report
        partial.table = pd.DataFrame({k: v for k, v in only.items()}).T
    if folder is None:
        return
    try:
        write_table(folder, partial.table)
    finally:
        folder.update(
            status="failed",
            error=f"{step} failed: {type(err).__name__}: {err}",
            failures=partial.failures,
            identifiability=partial.identifiability,
            validation_noise=partial.validation_noise,
        )
        partial.files = list(folder.files)


def _where(workers: int, scheduler: Any, n: int) -> str:
    """Where the calibrations run, for the progress line."""
    if scheduler is not None:
        where = scheduler if isinstance(scheduler, str) else "of the given client"
        return f" on the Dask cluster {where}"
    if workers > 1 and n > 1:
        return f" on a local Dask cluster of {workers} worker processes"
    return ""


def _checked_study(physics, validation, tolerance, workers, scheduler, formulations):
    """Check the study's inputs before any sampling; returns ε and the formulations."""
    tolerance = check_validation_data(physics, validation, tolerance)
    check_execution(workers, scheduler)
    formulations = dict(formulations or default_formulations(physics.inputs))
    if not formulations:
        raise ValueError("no formulations to run")
    return tolerance, formulations


def _collect(outcomes, reused, formulations, failures, say):
    """``(scored, wall)`` in the study's order, reused ones included (failures noted)."""
    scored: dict[str, Scored] = {}
    wall: dict[str, float] = {}
    for label in formulations:  # the formulations' order, whatever order they finished in
        if label in reused:
            scored[label] = reused[label]
            continue
        if label not in outcomes:
            continue
        outcome, seconds, error = outcomes[label]
        if error is not None:
            failures[label] = error
            say(f"  {label} FAILED: {error}")
            continue
        scored[label] = outcome
        wall[label] = seconds
        _say_scores(say, label, outcome, seconds)
    if not scored:
        raise RuntimeError(
            "every formulation failed: " + "; ".join(f"{k}: {v}" for k, v in failures.items())
        )
    return scored, wall


def _row(label, scored: Scored, results, identifiability) -> dict[str, Any]:
    """Posterior summary, convergence and identifiability columns of one formulation."""
    cal = scored.calibration
    params = list(cal.physics.parameters)
    diag = sampler_diagnostics(results[label], params)
    row: dict[str, Any] = {}
    for p in params:
        row[f"{p}_mean"] = float(diag.loc[p, "mean"])
        row[f"{p}_sd"] = float(diag.loc[p, "sd"])
    with single_chain_notes_hidden():
        row["r_hat_max"] = float(az.rhat(results[label].posterior).to_array().max())
    row["ess_bulk_min"] = float(diag["ess_bulk"].min())
    divergences = diag.attrs["divergences"]  # None: a sampler without them (SMC)
    row["divergences"] = None if divergences is None else int(divergences)
    row["validation_noise"] = describe_noise(scored.noise)
    row["identifiable"] = identifiability.get(label, {}).get("identifiable")
    problems = [*cal.problems, *physics_problems(cal.idata)]
    row["status"] = "ok" if not problems else "; ".join(problems)
    return row


def _table(formulations, scored, results, metrics, weights, loo, failures, identifiability):
    rows = []
    for label in [*formulations, COMBINED]:
        if label == COMBINED and COMBINED not in metrics:
            continue
        row: dict[str, Any] = {"formulation": label}
        row["description"] = (
            "reliability-weighted mixture" if label == COMBINED else formulations[label].description
        )
        row.update(metrics.get(label, {}))
        row["weight"] = weights.get(label, np.nan) if label != COMBINED else np.nan
        if loo is not None and label in loo.index:
            row["elpd_loo"] = float(loo.loc[label, "elpd_loo"])
            row["loo_weight"] = float(loo.loc[label, "weight"])
            row["max_pareto_k"] = float(loo.loc[label, "max_pareto_k"])
        if label in scored:
            row.update(_row(label, scored[label], results, identifiability))
        elif label == COMBINED:
            row["validation_noise"] = "mixture of each formulation's r(x)"
            row["status"] = "ok"
        else:
            row["status"] = f"failed: {failures.get(label, 'unknown')}"
        rows.append(row)
    frame = pd.DataFrame(rows).set_index("formulation")
    if "r_hat_max" in frame:
        frame.attrs["r_hat_limit"] = RHAT_MAX
    return frame
