"""The paper's three-step study (Sections 4–5): check, calibrate, validate, then weigh.

:func:`run_study` takes a physics model, calibration and validation data and a set of
discrepancy formulations, and

1. runs the Taylor identifiability check of every formulation before any sampling
   (:func:`kohpymc.identifiability.check_formulation`);
2. calibrates each formulation (:func:`kohpymc.calibrate`) and predicts at the
   validation inputs (:func:`kohpymc.predict`);
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

import json
import os
import time
import warnings
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr

from kohpymc.calibration import calibrate, predict
from kohpymc.combination import combine_posteriors, loo_weights, reliability_weights
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import RHAT_MAX, SamplerTroubleWarning, sampler_diagnostics
from kohpymc.discrepancy import (
    ConstantBias,
    Discrepancy,
    GaussianProcess,
    IIDGaussian,
    InputDependentGaussian,
    NoDiscrepancy,
    NonStationaryGP,
)
from kohpymc.identifiability import IdentifiabilityWarning, check_formulation
from kohpymc.physics import PhysicsModel
from kohpymc.reliability import reliability

__all__ = [
    "StudyResult",
    "run_study",
    "default_formulations",
    "markdown_table",
    "validation_metrics",
    "write_atomic",
]

COMBINED = "combined"


def default_formulations(
    inputs: Sequence[str], *, time: str | None = None
) -> dict[str, Discrepancy]:
    """M0–M4 with means (and M3's log-variance) linear in ``inputs``; M5 if ``time`` given.

    Examples
    --------
    >>> list(default_formulations(["x"]))
    ['M0', 'M1', 'M2', 'M3', 'M4']
    >>> list(default_formulations(["V", "t"], time="t"))[-1]
    'M5'
    """
    inputs = list(inputs)
    out: dict[str, Discrepancy] = {
        "M0": NoDiscrepancy(),
        "M1": ConstantBias(),
        "M2": IIDGaussian(),
        "M3": InputDependentGaussian(mean=inputs),
        "M4": GaussianProcess(inputs),
    }
    if time is not None:
        out["M5"] = NonStationaryGP(inputs, time=time)
    return out


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


def markdown_table(frame: pd.DataFrame, digits: int = 4) -> str:
    """A pipe table (GitHub Markdown) of a DataFrame, floats to ``digits`` significant.

    Examples
    --------
    >>> import pandas as pd
    >>> print(markdown_table(pd.DataFrame({"mu_r": [0.51234]}, index=["M1"])))
    | formulation | mu_r |
    |---|---|
    | M1 | 0.5123 |
    """

    def cell(v: Any) -> str:
        if isinstance(v, float | np.floating):
            return "" if np.isnan(v) else f"{v:.{digits}g}"
        return str(v).replace("|", "\\|")

    name = frame.index.name or "formulation"
    lines = ["| " + " | ".join([name, *map(str, frame.columns)]) + " |"]
    lines.append("|" + "---|" * (len(frame.columns) + 1))
    for idx, row in frame.iterrows():
        lines.append("| " + " | ".join([cell(idx), *(cell(v) for v in row)]) + " |")
    return "\n".join(lines)


def _check_inputs(physics: PhysicsModel, validation: CalibrationData, tolerance: float) -> None:
    if not np.isfinite(tolerance) or tolerance <= 0:
        raise ValueError(f"validation tolerance must be a positive number, got {tolerance!r}")
    where = f" ({validation.source})" if validation.source else ""
    if validation.n == 0:
        raise ValueError(f"validation data{where} are empty")
    missing = [k for k in physics.inputs if k not in validation.inputs]
    if missing:
        raise KeyError(
            f"validation data{where} lack input column(s) {missing} of the physics model "
            f"{physics.name!r}"
        )
    try:
        physics.evaluate({k: validation.inputs[k] for k in physics.inputs}, physics.prior_mean())
    except Exception as err:
        raise ValueError(
            f"validation data{where}: the physics model {physics.name!r} fails on the "
            f"validation inputs: {err}"
        ) from err


def _seed(random_seed: int | None, label: str, purpose: int) -> int | None:
    """A seed per (formulation, purpose), so adding a formulation changes no other's draws."""
    if random_seed is None:
        return None
    key = (zlib.crc32(label.encode()), purpose)
    return int(np.random.SeedSequence(random_seed, spawn_key=key).generate_state(1)[0])


def validation_metrics(
    pred: az.InferenceData, validation: CalibrationData, tolerance: float, noise_sd, weights
) -> tuple[dict[str, float], xr.Dataset]:
    """μ_r ± MCSE, RMSE of the posterior-mean ``y_model`` and 90 % coverage of ``y_pred``.

    Returns the scores and a Dataset (``reliability``, ``y_validation`` over ``pred``) for
    the ``predictions_constant_data`` group.
    """
    rel = reliability(pred, validation, tolerance, noise_sd=noise_sd, weights=weights)
    ym = pred.predictions["y_model"].transpose(..., "pred").values
    yp = pred.predictions["y_pred"].transpose(..., "pred").values
    ym = ym.reshape(-1, ym.shape[-1])
    yp = yp.reshape(-1, yp.shape[-1])
    lo, hi = np.quantile(yp, [0.05, 0.95], axis=0)
    metrics = {
        "mu_r": rel.mu_r,
        "mu_r_mcse": rel.mcse,
        "rmse": float(np.sqrt(np.mean((ym.mean(axis=0) - validation.y) ** 2))),
        "coverage90": float(np.mean((validation.y >= lo) & (validation.y <= hi))),
    }
    const = rel.to_dataset()
    const["y_validation"] = xr.DataArray(validation.y, dims=("pred",))
    return metrics, const


def _noise_sd_for_validation(
    validation: CalibrationData, calibration: CalibrationData, idata: az.InferenceData
) -> float | None:
    """σ of y_D: the validation data's, else the calibration data's, else calibrated σ_obs."""
    if validation.noise_sd is not None or validation.replicates is not None:
        return validation.noise_sd
    if calibration.noise_sd is not None:
        return calibration.noise_sd
    if "sigma_obs" in idata.posterior:
        return float(idata.posterior["sigma_obs"].mean())
    return None


def write_atomic(path: Path, write: Callable[[Path], None]) -> Path:
    """Write via ``write(tmp)`` to a hidden temporary name, then rename to ``path``.

    Nothing is left behind under either name when ``write`` fails.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "a.txt"
    >>> write_atomic(target, lambda p: p.write_text("ok")).read_text()
    'ok'
    """
    tmp = path.with_name(f".{path.name}.part")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _write_atomic(path: Path, write: Callable[[Path], None], files: list[Path]) -> None:
    files.append(write_atomic(path, write))


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


def _calibrate_one(job: _Job, label: str, disc: Discrepancy) -> tuple:
    """Calibrate, predict at the validation inputs and score one formulation."""
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SamplerTroubleWarning)
        idata = calibrate(
            job.physics,
            job.calibration,
            disc,
            random_seed=_seed(job.random_seed, label, 0),
            check_identifiability=False,
            **job.settings,
        )
    pred = predict(
        idata,
        job.physics,
        job.calibration,
        disc,
        job.validation,
        random_seed=_seed(job.random_seed, label, 1),
    )
    noise_sd = _noise_sd_for_validation(job.validation, job.calibration, idata)
    scores, const = validation_metrics(
        pred, job.validation, job.tolerance, noise_sd, job.validation_weights
    )
    return idata, pred, scores, const, time.perf_counter() - start


def _calibrate_one_safely(job: _Job, label: str, disc: Discrepancy) -> tuple[Any, str | None]:
    try:
        return _calibrate_one(job, label, disc), None
    except Exception as err:  # noqa: BLE001 - reported, the study goes on
        return None, f"{type(err).__name__}: {err}"


#: the study a forked worker process reads (set before the workers fork)
_FORKED: tuple[_Job, dict[str, Discrepancy]] | None = None


def _forked_worker(label: str) -> tuple[str, Any, str | None]:
    assert _FORKED is not None
    job, formulations = _FORKED
    outcome, error = _calibrate_one_safely(job, label, formulations[label])
    return label, outcome, error


def _run_forked(job: _Job, formulations: dict[str, Discrepancy], labels: list[str], workers: int):
    """Yield ``(label, outcome, error)`` as formulations finish in ``workers`` processes.

    The processes are forked, so the physics function, data and formulations need not be
    picklable (only the results travel back).
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    global _FORKED
    try:
        context = multiprocessing.get_context("fork")
    except ValueError as err:  # pragma: no cover - Windows
        raise ValueError("workers > 1 needs the 'fork' start method (Linux, macOS)") from err
    _FORKED = (job, formulations)
    try:
        with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            futures = {pool.submit(_forked_worker, label): label for label in labels}
            for future in as_completed(futures):
                try:
                    yield future.result()
                except Exception as err:  # noqa: BLE001 - e.g. a worker killed by the OS
                    yield futures[future], None, f"worker process: {type(err).__name__}: {err}"
    finally:
        _FORKED = None


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
        Default :func:`default_formulations` over the physics inputs (M0–M4).
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
        Formulations calibrated at the same time, each in its own (forked) process.
        The results are the same as with ``workers=1`` (every formulation's seed comes
        from ``random_seed`` and its label).  With ``workers`` equal to the number of
        cores, pass ``cores=1`` so the chains of each run one after the other; this also
        overlaps the single-threaded compilation and prediction steps of different
        formulations.
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
    _check_inputs(physics, validation, tolerance)
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    if formulations is None:
        formulations = default_formulations(physics.inputs)
    formulations = dict(formulations)
    if not formulations:
        raise ValueError("no formulations to run")
    params = list(physics.parameters)

    say(f"identifiability check of {len(formulations)} formulation(s) at the prior centre")
    identifiability: dict[str, dict] = {}
    failures: dict[str, str] = {}
    for label, disc in formulations.items():
        try:
            report = check_formulation(physics, calibration, disc)
        except Exception as err:  # noqa: BLE001 - reported, the study goes on
            failures[label] = f"identifiability check failed: {type(err).__name__}: {err}"
            say(f"  {label}: {failures[label]}")
            continue
        identifiability[label] = report.to_dict()
        if report.identifiable:
            say(f"  {label}: identifiable (rank {report.rank} of {len(report.names)})")
        else:
            text = "; ".join(report.confounded())
            say(f"  {label}: NOT identifiable (rank {report.rank}/{len(report.names)}): {text}")
            warnings.warn(
                f"{label} is not identifiable at the prior centre: {text}",
                IdentifiabilityWarning,
                stacklevel=2,
            )

    job = _Job(
        physics=physics,
        calibration=calibration,
        validation=validation,
        tolerance=tolerance,
        validation_weights=validation_weights,
        random_seed=random_seed,
        settings=dict(
            draws=draws,
            tune=tune,
            chains=chains,
            target_accept=target_accept,
            progressbar=progressbar,
            **calibrate_kwargs,
        ),
    )
    todo = [label for label in formulations if label not in failures]
    position = {label: i + 1 for i, label in enumerate(formulations)}
    outcomes: dict[str, tuple[Any, str | None]] = {}
    if workers > 1 and len(todo) > 1:
        say(f"calibrating {len(todo)} formulation(s), {workers} at a time")
        for label, outcome, error in _run_forked(job, formulations, todo, workers):
            outcomes[label] = (outcome, error)
            say(f"[{position[label]}/{len(formulations)}] {label} finished")
    else:
        for label in todo:
            disc = formulations[label]
            say(
                f"[{position[label]}/{len(formulations)}] {label} ({disc.description}): "
                "calibrating ..."
            )
            outcomes[label] = _calibrate_one_safely(job, label, disc)

    results: dict[str, az.InferenceData] = {}
    metrics: dict[str, dict[str, float]] = {}
    wall: dict[str, float] = {}
    for label in todo:  # the formulations' order, whatever order they finished in
        outcome, error = outcomes[label]
        if error is not None:
            failures[label] = error
            say(f"  {label} FAILED: {error}")
            continue
        idata, pred, scores, const, seconds = outcome
        idata.extend(pred)
        idata.add_groups(predictions_constant_data=const)
        if label in identifiability:
            idata.attrs["identifiability"] = json.dumps(identifiability[label])
        idata.attrs.update({k: float(v) for k, v in scores.items()})
        results[label] = idata
        metrics[label] = scores
        wall[label] = seconds
        problems = json.loads(idata.attrs["sampler_problems"])
        say(
            f"  {label}: mu_r = {scores['mu_r']:.3f} ± {scores['mu_r_mcse']:.3f}, "
            f"RMSE {scores['rmse']:.3g}, 90% coverage {scores['coverage90']:.2f}, "
            f"{seconds:.0f} s" + (f"; sampler: {'; '.join(problems)}" if problems else "")
        )
    if not results:
        raise RuntimeError(
            "every formulation failed: " + "; ".join(f"{k}: {v}" for k, v in failures.items())
        )

    positive = {k: m["mu_r"] for k, m in metrics.items()}
    weights = reliability_weights(positive) if sum(positive.values()) > 0 else {}
    loo = None
    if len(results) >= 2:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                loo = loo_weights(results)
        except Exception as err:  # noqa: BLE001 - LOO is a side comparison
            say(f"LOO comparison skipped: {err}")
    combined = None
    if weights:
        combined = combine_posteriors(
            results,
            weights,
            var_names=params,
            predictions=results,
            random_seed=_seed(random_seed, COMBINED, 2),
        )
        noise_sd = _noise_sd_for_validation(validation, calibration, combined)
        scores, const = validation_metrics(
            combined, validation, tolerance, noise_sd, validation_weights
        )
        # r(x) is linear in the predictive distribution, so the mixture's μ_r is exactly
        # Σ w_i μ_r,i; use that rather than the resampled draws' noisier estimate
        labels = list(weights)
        scores["mu_r"] = float(sum(weights[k] * metrics[k]["mu_r"] for k in labels))
        scores["mu_r_mcse"] = float(
            np.sqrt(sum((weights[k] * metrics[k]["mu_r_mcse"]) ** 2 for k in labels))
        )
        const.attrs.update({"mu_r": scores["mu_r"], "mu_r_mcse": scores["mu_r_mcse"]})
        combined.add_groups(predictions_constant_data=const)
        combined.attrs.update({k: float(v) for k, v in scores.items()})
        metrics[COMBINED] = scores

    table = _table(formulations, results, metrics, weights, loo, failures, identifiability, params)
    result = StudyResult(
        results=results,
        table=table,
        weights=weights,
        loo=loo,
        combined=combined,
        failures=failures,
        identifiability=identifiability,
        wall_time_s=wall,
    )
    if out_dir is not None:
        _write(result, Path(out_dir), physics, validation, figures, reference)
        say(f"wrote {len(result.files)} files to {out_dir}")
    return result


def _table(formulations, results, metrics, weights, loo, failures, identifiability, params):
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
        idata = results.get(label)
        if idata is not None:
            diag = sampler_diagnostics(idata, params)
            for p in params:
                row[f"{p}_mean"] = float(diag.loc[p, "mean"])
                row[f"{p}_sd"] = float(diag.loc[p, "sd"])
            row["r_hat_max"] = float(az.rhat(idata.posterior).to_array().max())
            row["ess_bulk_min"] = float(diag["ess_bulk"].min())
            row["divergences"] = int(diag.attrs["divergences"])
            row["identifiable"] = identifiability.get(label, {}).get("identifiable")
            problems = json.loads(idata.attrs["sampler_problems"])
            row["status"] = "ok" if not problems else "; ".join(problems)
        elif label == COMBINED:
            row["status"] = "ok"
        else:
            row["status"] = f"failed: {failures.get(label, 'unknown')}"
        rows.append(row)
    frame = pd.DataFrame(rows).set_index("formulation")
    if "r_hat_max" in frame:
        frame.attrs["r_hat_limit"] = RHAT_MAX
    return frame


def _write(
    result: StudyResult,
    out: Path,
    physics: PhysicsModel,
    validation: CalibrationData,
    figures: bool,
    reference: Mapping[str, float] | None,
) -> None:
    import matplotlib.pyplot as plt

    from kohpymc.plots import (
        plot_parameter_posteriors,
        plot_reliability,
        plot_validation_predictions,
    )

    out.mkdir(parents=True, exist_ok=True)
    files = result.files
    for label, idata in result.results.items():
        _write_atomic(out / f"{label}.nc", lambda p, d=idata: d.to_netcdf(str(p)), files)
    if result.combined is not None:
        _write_atomic(out / f"{COMBINED}.nc", lambda p: result.combined.to_netcdf(str(p)), files)
    _write_atomic(out / "table.csv", lambda p: result.table.to_csv(p), files)
    _write_atomic(
        out / "table.md", lambda p: p.write_text(markdown_table(result.table) + "\n"), files
    )
    summary = {
        "weights": result.weights,
        "loo_weights": (
            {} if result.loo is None else {k: float(v) for k, v in result.loo["weight"].items()}
        ),
        "failures": result.failures,
        "identifiability": result.identifiability,
        "wall_time_s": result.wall_time_s,
    }
    _write_atomic(
        out / "study.json", lambda p: p.write_text(json.dumps(summary, indent=2) + "\n"), files
    )
    if not figures:
        return
    params = list(physics.parameters)
    figs = {
        "posteriors.png": plot_parameter_posteriors(
            result.results, params, combined=result.combined, reference=reference
        ),
        "reliability.png": plot_reliability(result.table),
    }
    preds = dict(result.results)
    if result.combined is not None:
        preds[COMBINED] = result.combined
    names = [k for k in validation.inputs if k in physics.inputs] or list(validation.inputs)
    figs["predictions.png"] = plot_validation_predictions(
        preds,
        validation.y,
        {k: validation.inputs[k] for k in names},
        output_name=validation.output_name,
    )
    for name, fig in figs.items():
        _write_atomic(out / name, lambda p, f=fig: f.savefig(p, dpi=120, format="png"), files)
        plt.close(fig)
