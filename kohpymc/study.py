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

A formulation that fails (an exception while building, sampling or predicting) is
reported in the table and does not stop the others.  With ``out_dir`` the results are
written as ``<label>.nc`` per formulation, ``combined.nc``, ``table.csv``, ``table.md``,
``study.json`` and three figures; every file is written to a temporary name first and
renamed when complete.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import arviz as az
import numpy as np
import pandas as pd

from kohpymc.calibration import Calibration
from kohpymc.checks import check_execution, check_validation_data
from kohpymc.combination import combine_posteriors, loo_weights, reliability_weights
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import RHAT_MAX, sampler_diagnostics
from kohpymc.discrepancy import Discrepancy
from kohpymc.discrepancy.defaults import default_formulations
from kohpymc.execution import run_tasks, runs_remotely
from kohpymc.identifiability import IdentifiabilityWarning, check_formulation
from kohpymc.model import compose_model
from kohpymc.physics import PhysicsModel
from kohpymc.progress import LineDisplay, TaskDisplay
from kohpymc.study_files import COMBINED, _write, markdown_table, write_atomic
from kohpymc.validation import (
    Scored,
    derived_seed,
    fit_and_score,
    validation_metrics,
    validation_noise_sd,
)

__all__ = [
    "StudyResult",
    "run_study",
    "markdown_table",
    "write_atomic",
]


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
    noise_sd : dict label -> float or None
        σ of y_D used in each formulation's reliability integral.
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
    noise_sd: dict[str, float | None] = field(default_factory=dict)

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
            return view.to_string(float_format=lambda v: f"{v:.4g}")


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
            check_identifiability=False,
            **self.settings,
        )

    def fit_remotely(self, label: str, disc: Discrepancy) -> tuple:
        """:meth:`fit` on a Dask worker: only picklable results travel back (no model)."""
        scored = self.fit(label, disc)
        cal = scored.calibration
        payload = (cal.idata, cal.problems, cal.identifiability, cal.noise_sd_prior)
        return payload, (scored.predictions, scored.scores, scored.constant, scored.noise_sd)


def _rebuilt(job: _Job, disc: Discrepancy, payload: tuple) -> Scored:
    """A worker's results as a Scored, with the model rebuilt here (building is cheap)."""
    (idata, problems, report, noise_prior), rest = payload
    built = compose_model(job.physics, job.calibration, disc, noise_sd_prior=noise_prior)
    cal = Calibration(
        job.physics, job.calibration, disc, built, idata, problems, report, noise_prior
    )
    return Scored(cal, *rest)


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
            say(f"  {label}: identifiable (rank {report.rank} of {len(report.names)})")
        else:
            text = "; ".join(report.confounded())
            say(f"  {label}: NOT identifiable (rank {report.rank}/{len(report.names)}): {text}")
            warnings.warn(
                f"{label} is not identifiable at the prior centre: {text}",
                IdentifiabilityWarning,
                stacklevel=3,
            )
    return reports, failures


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
    """Reliability weights (Eq. 23) and the weighted mixture (Eq. 24) with its scores."""
    params = list(job.physics.parameters)
    calibration, validation, tolerance = job.calibration, job.validation, job.tolerance
    weights_v = job.validation_weights
    positive = {k: m["mu_r"] for k, m in metrics.items()}
    weights = reliability_weights(positive) if sum(positive.values()) > 0 else {}
    if not weights:
        return weights, None, None
    combined = combine_posteriors(
        results, weights, var_names=params, predictions=results, random_seed=seed
    )
    noise_sd = validation_noise_sd(validation, calibration, combined["posterior"])
    scores, const = validation_metrics(combined, validation, tolerance, noise_sd, weights_v)
    # r(x) is linear in the predictive distribution, so the mixture's μ_r is exactly
    # Σ w_i μ_r,i; use that rather than the resampled draws' noisier estimate
    scores["mu_r"] = float(sum(w * metrics[k]["mu_r"] for k, w in weights.items()))
    scores["mu_r_mcse"] = float(
        np.sqrt(sum((w * metrics[k]["mu_r_mcse"]) ** 2 for k, w in weights.items()))
    )
    const.attrs.update({"mu_r": scores["mu_r"], "mu_r_mcse": scores["mu_r_mcse"]})
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
    **calibrate_kwargs: Any,
) -> StudyResult:
    """Check, calibrate, validate and weigh a set of discrepancy formulations.

    Runs the identifiability check, calibrations, validation metrics, weights and the
    mixture, optionally writing everything to ``out_dir``.

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
        Folder to write results to (created if needed).
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
    **calibrate_kwargs :
        Further keywords for :func:`kohpymc.calibrate`.

    Returns
    -------
    StudyResult

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
    todo = [label for label in formulations if label not in failures]
    # one formulation: no cluster to start (an existing one is used as asked)
    execution = {"workers": workers if len(todo) > 1 else 1, "scheduler": scheduler}
    say(f"calibrating {len(todo)} formulation(s)" + _where(workers, scheduler, len(todo)))
    outcomes = {
        label: (scored, seconds, error)
        for label, scored, seconds, error in _calibrate_all(
            job, formulations, todo, execution, display
        )
    }
    display.close()
    scored, wall = _collect(outcomes, todo, failures, say)
    results = {k: s.combined_idata() for k, s in scored.items()}
    metrics = {k: s.scores for k, s in scored.items()}
    loo = _loo_comparison(results, say)
    weights, combined, combined_scores = _mixture(
        results, metrics, job, derived_seed(random_seed, COMBINED, 2)
    )
    if combined_scores is not None:
        metrics[COMBINED] = combined_scores
    table = _table(formulations, scored, results, metrics, weights, loo, failures, identifiability)
    result = StudyResult(
        results=results,
        table=table,
        weights=weights,
        loo=loo,
        combined=combined,
        failures=failures,
        identifiability=identifiability,
        wall_time_s=wall,
        calibrations={k: s.calibration for k, s in scored.items()},
        noise_sd={k: s.noise_sd for k, s in scored.items()},
    )
    if out_dir is not None:
        _write(result, Path(out_dir), physics, validation, figures, reference)
        say(f"wrote {len(result.files)} files to {out_dir}")
    return result


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


def _collect(outcomes, todo, failures, say) -> tuple[dict[str, Scored], dict[str, float]]:
    """Scored formulations in the study's order (failures go into ``failures``)."""
    scored: dict[str, Scored] = {}
    wall: dict[str, float] = {}
    for label in todo:  # the formulations' order, whatever order they finished in
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
    row["r_hat_max"] = float(az.rhat(results[label].posterior).to_array().max())
    row["ess_bulk_min"] = float(diag["ess_bulk"].min())
    row["divergences"] = int(diag.attrs["divergences"])
    row["identifiable"] = identifiability.get(label, {}).get("identifiable")
    row["status"] = "ok" if not cal.problems else "; ".join(cal.problems)
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
            row["status"] = "ok"
        else:
            row["status"] = f"failed: {failures.get(label, 'unknown')}"
        rows.append(row)
    frame = pd.DataFrame(rows).set_index("formulation")
    if "r_hat_max" in frame:
        frame.attrs["r_hat_limit"] = RHAT_MAX
    return frame
