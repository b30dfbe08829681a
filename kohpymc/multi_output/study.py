"""Run a multi-output study: every formulation calibrated on all outputs, then scored.

:func:`run_multi_output_study` calibrates each ``[formulations]`` entry of a
:class:`~kohpymc.multi_output.config.MultiOutputStudySpec` jointly on all outputs and
scores it on the validation data per output and combined
(:func:`~kohpymc.multi_output.reliability.output_reliability`).

With an output folder, each formulation's ``<label>.nc`` is written atomically the moment
it is sampled, with the fingerprint of everything its posterior depends on; a later run
into the same folder reuses a file whose fingerprint still matches (the model is rebuilt,
which is cheap, and the validation scores are recomputed).  A formulation that fails is
recorded in the manifest and in :attr:`MultiOutputStudyResult.failures`; the others go on.

The formulations run in this process one after the other, or as tasks on a Dask
cluster exactly as a single-output study's do (``workers``, ``scheduler`` or the file's
``[execution]``; :func:`kohpymc.execution.run_tasks`): a worker calibrates and predicts,
the draws come back, and this process rebuilds the model, writes the file and scores it.

**Reliability-weighted averaging** (paper Eqs. 23–24, as for one output): each finished
formulation's weight is its combined row's μ_r over the sum of them
(:func:`kohpymc.combination.reliability_weights`), and the weighted mixture of the
posteriors of θ (:func:`kohpymc.combination.combine_posteriors`) is
:attr:`MultiOutputStudyResult.combined`, written to ``combined.nc``; the weights are the
table's ``weight`` column (on the combined rows) and ``weights`` in ``study.json``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator, Mapping
from contextlib import closing
from dataclasses import dataclass, field, replace
from typing import Any

import arviz as az
import pandas as pd

from kohpymc.calibration import physics_problems
from kohpymc.checks import check_execution
from kohpymc.combination import combine_posteriors, reliability_weights
from kohpymc.execution import run_tasks, runs_remotely
from kohpymc.fingerprint import (
    data_fingerprint,
    digest,
    formulation_fingerprint,
    kohpymc_version,
    physics_fingerprint,
)
from kohpymc.multi_output.calibration import (
    MultiOutputCalibration,
    calibrate_outputs,
    predict_output,
)
from kohpymc.multi_output.config import MultiOutputStudySpec
from kohpymc.multi_output.loo import output_loo
from kohpymc.multi_output.model import compose_multi_output_model
from kohpymc.multi_output.reliability import COMBINED, OutputReliability, output_reliability
from kohpymc.progress import LineDisplay, TaskDisplay
from kohpymc.study import _where
from kohpymc.study_files import (
    CALIBRATION_HASH,
    StudyFolder,
    calibration_part,
    write_figures,
    write_table,
)
from kohpymc.validation import derived_seed

__all__ = ["MultiOutputStudyResult", "run_multi_output_study"]


@dataclass
class MultiOutputStudyResult:
    """Calibrations and reliabilities per formulation label.

    Attributes
    ----------
    calibrations : dict of str to MultiOutputCalibration
    reliabilities : dict of str to OutputReliability
    failures : dict of str to str
        Formulations that failed, with the error.
    reused : list of str
        Formulations whose posterior was read from an earlier run's file.
    predictions : dict of str to dict of str to InferenceData
        Label -> output -> predictions at that output's validation inputs.
    loo : pandas.DataFrame or None
        LOO comparison on the calibration data per output and combined
        (:func:`~kohpymc.multi_output.loo.output_loo`; with two or more finished
        formulations), its columns also in :attr:`table`.
    weights : dict of str to float
        Reliability weights (Eq. 23) from each formulation's combined μ_r (empty when
        every μ_r is 0).
    combined : arviz.InferenceData or None
        The weighted mixture of the posteriors of θ (Eq. 24), with a ``formulation``
        coordinate on ``draw``.
    """

    calibrations: dict[str, MultiOutputCalibration]
    reliabilities: dict[str, OutputReliability]
    failures: dict[str, str] = field(default_factory=dict)
    reused: list[str] = field(default_factory=list)
    predictions: dict[str, dict[str, az.InferenceData]] = field(default_factory=dict)
    loo: pd.DataFrame | None = None
    weights: dict[str, float] = field(default_factory=dict)
    combined: az.InferenceData | None = None

    @property
    def table(self) -> pd.DataFrame:
        """μ_r per (formulation, output) and combined, θ means/sds and sampler problems.

        With weights, a ``weight`` column holds each formulation's reliability weight on
        its combined row.
        """
        frames = []
        for label, rel in self.reliabilities.items():
            frame = rel.table[["n", "tolerance", "mu_r", "mu_r_mcse"]].copy()
            post = self.calibrations[label].posterior
            for name in self.calibrations[label].physics.parameter_names:
                frame[f"{name} mean"] = float(post[name].mean())
                frame[f"{name} sd"] = float(post[name].std())
            cal = self.calibrations[label]
            frame["sampler_problems"] = "; ".join(cal.problems) or "none"
            frame["physics_problems"] = "; ".join(physics_problems(cal.idata)) or "none"
            frames.append(frame.assign(formulation=label).reset_index())
        if not frames:
            raise ValueError(f"no formulation finished; failures: {self.failures}")
        table = pd.concat(frames).set_index(["formulation", "output"])
        if self.weights:
            rows = [(label, COMBINED) for label in self.weights]
            table["weight"] = pd.Series(
                list(self.weights.values()), index=pd.MultiIndex.from_tuples(rows)
            )
        return table if self.loo is None else table.join(self.loo)


def run_multi_output_study(
    spec: MultiOutputStudySpec,
    *,
    out_dir: str | os.PathLike[str] | None = None,
    fresh: bool = False,
    figures: bool = True,
    progress: Callable[[str], None] | None = None,
    workers: int | None = None,
    scheduler: Any = None,
    display: TaskDisplay | None = None,
    **overrides: Any,
) -> MultiOutputStudyResult:
    """Calibrate and score every formulation of a multi-output study.

    Parameters
    ----------
    spec : MultiOutputStudySpec
    out_dir : path, optional
        Output folder: ``<label>.nc`` per formulation as it finishes, ``study.json``,
        ``table.csv`` and ``table.md`` at the end, each written atomically.  Files of an
        earlier run whose fingerprint matches are reused.
    fresh : bool
        Ignore earlier files in ``out_dir``.
    figures : bool
        With ``out_dir``: ``posteriors.png`` (θ per formulation) and
        ``predictions_<output>.png`` (validation predictions per formulation).
    progress : callable, optional
        Receives one line per step (``print`` for a terminal).
    workers, scheduler :
        Where the formulations run, as in :func:`kohpymc.run_study`: ``workers > 1``
        starts a local Dask cluster of that many processes, ``scheduler`` (an address
        or a ``distributed.Client``) uses an existing one
        (:func:`kohpymc.execution.run_tasks`).  Default the file's ``[execution]``
        (in this process when it has none).  Each formulation's seed comes from the
        study's seed and its label, so the draws are the same wherever it runs.
    display : TaskDisplay, optional
        Shows each formulation queued, running, done or failed; default plain lines
        through ``progress``.
    **overrides :
        Replace sampler settings of the file (e.g. ``draws=300``).

    Returns
    -------
    MultiOutputStudyResult

    Raises
    ------
    ValueError
        ``workers`` not a positive integer, or both ``workers > 1`` and ``scheduler``.

    Examples
    --------
    >>> result = run_multi_output_study(spec, draws=300, tune=300)  # doctest: +SKIP
    >>> result.table.loc["M0"].index.tolist()  # doctest: +SKIP
    ['u', 'strain', 'combined']
    """
    execution = _execution(spec, workers, scheduler)
    say = progress or (lambda message: None)
    display = display or (LineDisplay(say) if progress else TaskDisplay())
    folder = None if out_dir is None else StudyFolder(out_dir, fresh=fresh)
    job = _Job(spec, {**spec.sampling, **overrides})
    result = MultiOutputStudyResult({}, {})
    todo = _reuse_finished(job, folder, result, say)
    if len(todo) < 2:  # one formulation: no cluster to start (an existing one is used)
        execution["workers"] = 1
    if todo:
        say(f"calibrating {len(todo)} formulation(s)" + _where(**execution, n=len(todo)))
    for label, cal, predictions, error in _calibrate_all(job, todo, execution, display):
        if cal is not None:  # None when the task failed (error says why)
            error = _keep(job, folder, label, cal, predictions, result)
        if error is not None:
            result.failures[label] = error
            if folder is not None:
                folder.record(label, status="failed", error=error)
    display.close()
    result = _in_study_order(result, list(spec.formulations))
    result.loo = _loo_comparison(result, spec, say)
    result.weights, result.combined = _mixture(result, spec, job.seed)
    if folder is not None:
        _write_study_files(folder, result, spec, figures)
    return result


def _mixture(
    result: MultiOutputStudyResult, spec: MultiOutputStudySpec, seed: int | None
) -> tuple[dict[str, float], az.InferenceData | None]:
    """Weights from the combined rows' μ_r (Eq. 23) and the mixture of θ (Eq. 24)."""
    mu_r = {
        label: float(rel.table.loc[COMBINED, "mu_r"]) for label, rel in result.reliabilities.items()
    }
    if not mu_r or sum(mu_r.values()) <= 0:
        return {}, None
    weights = reliability_weights(mu_r)
    idatas = {label: result.calibrations[label].idata for label in weights}
    combined = combine_posteriors(
        idatas, weights, var_names=list(spec.physics.parameter_names),
        random_seed=derived_seed(seed, COMBINED, 2),
    )  # fmt: skip
    return weights, combined


def _loo_comparison(
    result: MultiOutputStudyResult, spec: MultiOutputStudySpec, say: Callable[[str], None]
) -> pd.DataFrame | None:
    """LOO per output and combined over the finished formulations (a side comparison)."""
    if len(result.calibrations) < 2:
        return None
    try:
        idatas = {label: cal.idata for label, cal in result.calibrations.items()}
        return output_loo(idatas, spec.calibration.outputs)
    except Exception as err:  # noqa: BLE001 - LOO is a side comparison, as for one output
        say(f"LOO comparison skipped: {_describe(err)}")
        return None


def _execution(spec: MultiOutputStudySpec, workers: int | None, scheduler: Any) -> dict[str, Any]:
    """``workers`` / ``scheduler`` given here, else the file's ``[execution]`` (checked)."""
    if workers is None and scheduler is None:
        execution = {"workers": 1, "scheduler": None, **spec.execution}
    else:
        execution = {"workers": 1 if workers is None else workers, "scheduler": scheduler}
    check_execution(execution["workers"], execution["scheduler"])
    return execution


@dataclass
class _Job:
    """What every formulation's calibration in a study shares (travels to the workers)."""

    spec: MultiOutputStudySpec
    settings: dict[str, Any]

    @property
    def seed(self) -> int | None:
        return self.settings.get("random_seed")

    def fit(self, label: str, formulation: Any) -> tuple[MultiOutputCalibration, dict]:
        """Calibrate one formulation and predict its outputs at the validation inputs."""
        cal = calibrate_outputs(
            self.spec.physics,
            self.spec.calibration,
            formulation,
            **{**self.settings, "random_seed": derived_seed(self.seed, label, 0)},
        )
        return cal, self.predict(label, cal)

    def fit_remotely(self, label: str, formulation: Any) -> tuple:
        """:meth:`fit` on a Dask worker: only picklable results travel back (no model)."""
        cal, predictions = self.fit(label, formulation)
        return (cal.idata, cal.problems, cal.identifiability), predictions

    def predict(self, label: str, cal: MultiOutputCalibration) -> dict[str, az.InferenceData]:
        """Each calibrated output's predictions at its validation inputs (seeded per label)."""
        seed = derived_seed(self.seed, label, 1)
        validation = self.spec.validation
        return {
            k: predict_output(cal, k, validation[k], random_seed=seed)
            for k in validation.outputs
            if k in cal.outputs
        }

    def rebuild(
        self, formulation: Any, idata: az.InferenceData, problems: list[str], report: Any = None
    ) -> MultiOutputCalibration:
        """A calibration around finished draws, its model rebuilt here (building is cheap)."""
        noise_prior = self.settings.get("noise_sd_prior")
        spec = self.spec
        built = compose_multi_output_model(
            spec.physics, spec.calibration, formulation, noise_sd_prior=noise_prior
        )
        return MultiOutputCalibration(
            spec.physics, spec.calibration, formulation, built, idata, problems, report,
            noise_prior,
        )  # fmt: skip


def _reuse_finished(
    job: _Job, folder: StudyFolder | None, result: MultiOutputStudyResult, say
) -> list[str]:
    """Score the formulations whose earlier files are still valid; the labels left to run."""
    if folder is None:
        return list(job.spec.formulations)
    todo = []
    for label, formulation in job.spec.formulations.items():
        cal = _reusable(job, folder, label, formulation)
        if cal is None:
            todo.append(label)
            folder.record(label, status="queued")
            continue
        result.reused.append(label)
        try:
            error = _keep(job, folder, label, cal, job.predict(label, cal), result)
        except Exception as err:  # noqa: BLE001 - reported, the study goes on
            error = _describe(err)
        if error is not None:
            result.failures[label] = error
            folder.record(label, status="failed", error=error)
        else:
            say(f"  {label}: reused ({folder.formulation_file(label)})")
    return todo


def _calibrate_all(
    job: _Job, todo: list[str], execution: dict[str, Any], display: TaskDisplay
) -> Iterator[tuple[str, MultiOutputCalibration | None, dict, str | None]]:
    """Yield ``(label, calibration, predictions, error)`` as formulations finish.

    In this process, or as tasks on a Dask cluster (:func:`kohpymc.execution.run_tasks`),
    whose results get their model rebuilt here.
    """
    remote = runs_remotely(**execution)
    task = job.fit_remotely if remote else job.fit
    items = {label: job.spec.formulations[label] for label in todo}
    with closing(run_tasks(task, items, progress=display, **execution)) as outcomes:
        for outcome in outcomes:
            if outcome.error is not None:
                yield outcome.key, None, {}, outcome.error
                continue
            cal, predictions = outcome.value
            if remote:
                try:
                    cal = job.rebuild(items[outcome.key], *cal)
                except Exception as err:  # noqa: BLE001 - reported, the study goes on
                    yield outcome.key, None, {}, f"rebuilding the model: {_describe(err)}"
                    continue
            yield outcome.key, cal, predictions, None


def _describe(err: BaseException) -> str:
    return f"{type(err).__name__}: {err}"


def _keep(
    job: _Job,
    folder: StudyFolder | None,
    label: str,
    cal: MultiOutputCalibration,
    predictions: dict[str, az.InferenceData],
    result: MultiOutputStudyResult,
) -> str | None:
    """Save a finished formulation (new ones), score it; the error if that fails."""
    reused = label in result.reused
    try:
        if folder is not None and not reused:
            _save(
                folder, label, cal, calibration_hash(job.spec, label, cal.discrepancy, job.settings)
            )
        reliability = output_reliability(
            cal, job.spec.validation, job.spec.tolerance, predictions=predictions,
            weights=job.spec.validation_weights,
        )  # fmt: skip
    except Exception as err:  # noqa: BLE001 - reported, the study goes on
        return _describe(err)
    result.calibrations[label] = cal
    result.predictions[label] = predictions
    result.reliabilities[label] = reliability
    if folder is not None:
        status = "reused" if reused else "done"
        folder.record(label, status=status, file=f"{label}.nc", sampler_problems=cal.problems)
    return None


def _in_study_order(result: MultiOutputStudyResult, labels: list[str]) -> MultiOutputStudyResult:
    """The result's per-formulation dicts in the file's order (tasks finish in any order)."""

    def ordered(mapping: dict) -> dict:
        return {k: mapping[k] for k in labels if k in mapping}

    return replace(
        result,
        calibrations=ordered(result.calibrations),
        reliabilities=ordered(result.reliabilities),
        failures=ordered(result.failures),
        reused=[k for k in labels if k in result.reused],
        predictions=ordered(result.predictions),
    )


def calibration_hash(
    spec: MultiOutputStudySpec, label: str, formulation: Any, settings: Mapping[str, Any]
) -> str:
    """Fingerprint of everything one formulation's joint posterior depends on.

    The physics of each output, each output's calibration data, the formulation (per
    output, or the joint one), the label, the sampler settings except those that change no
    draw (``progressbar``, ``cores``, ``warn``) and the kohpymc version.

    Examples
    --------
    >>> calibration_hash(spec, "M0", "none", {"draws": 300})  # doctest: +SKIP
    '3f9c...'
    """
    quiet = ("progressbar", "cores", "warn")
    if isinstance(formulation, Mapping):
        described: Any = {k: formulation_fingerprint(v) for k, v in formulation.items()}
    else:
        described = formulation_fingerprint(formulation)
    outputs = spec.calibration.outputs
    return digest(
        {
            "kohpymc": kohpymc_version(),
            "physics": {k: physics_fingerprint(spec.physics.output(k)) for k in outputs},
            "data": {k: data_fingerprint(spec.calibration[k]) for k in outputs},
            "formulation": described,
            "label": label,
            "settings": {k: v for k, v in settings.items() if k not in quiet},
        }
    )


def _reusable(
    job: _Job, folder: StudyFolder, label: str, formulation: Any
) -> MultiOutputCalibration | None:
    """The formulation's calibration from an earlier file with the same fingerprint, or None."""
    earlier = folder.finished(label)
    fingerprint = calibration_hash(job.spec, label, formulation, job.settings)
    if earlier is None or earlier.attrs.get(CALIBRATION_HASH) != fingerprint:
        return None
    idata = calibration_part(earlier)
    attrs = dict(earlier.attrs)
    problems = json.loads(attrs.pop("sampler_problems", "[]"))
    idata.attrs.update(attrs)
    return job.rebuild(formulation, idata, problems)


def _save(folder: StudyFolder, label: str, cal: MultiOutputCalibration, fingerprint: str) -> None:
    """Write the formulation's InferenceData at once, with its fingerprint and problems."""
    idata = cal.idata.copy()
    idata.attrs[CALIBRATION_HASH] = fingerprint
    idata.attrs["sampler_problems"] = json.dumps(list(cal.problems))
    folder.save_formulation(label, lambda path: idata.to_netcdf(str(path)))


def _write_study_files(
    folder: StudyFolder, result: MultiOutputStudyResult, spec: MultiOutputStudySpec, figures: bool
) -> None:
    """The table and figures (when anything finished) and the manifest's final state."""
    if result.combined is not None:
        combined = result.combined
        folder.write(f"{COMBINED}.nc", lambda path: combined.to_netcdf(str(path)))
    if result.reliabilities:
        write_table(folder, result.table)
        if figures:
            _write_figures(folder, result, spec)
    status = "failed" if not result.reliabilities else "done"
    loo = {} if result.loo is None else _loo_weights(result.loo)
    folder.update(
        status=status, failures=result.failures, reused=result.reused, loo_weights=loo,
        weights=result.weights,
    )  # fmt: skip


def _loo_weights(loo: pd.DataFrame) -> dict[str, dict[str, float]]:
    """Output (or ``"combined"``) -> formulation -> LOO stacking weight, for the manifest."""
    weights: dict[str, dict[str, float]] = {}
    for (label, output), weight in loo["loo_weight"].items():
        weights.setdefault(str(output), {})[str(label)] = float(weight)
    return weights


def _write_figures(
    folder: StudyFolder, result: MultiOutputStudyResult, spec: MultiOutputStudySpec
) -> None:
    """``posteriors.png`` and one ``predictions_<output>.png`` per validated output."""
    from kohpymc.plots import plot_parameter_posteriors, plot_validation_predictions

    posteriors = {label: cal.idata for label, cal in result.calibrations.items()}
    figs = {"posteriors.png": plot_parameter_posteriors(posteriors, spec.physics.parameter_names)}
    for k in spec.validation.outputs:
        preds = {label: p[k] for label, p in result.predictions.items() if k in p}
        if not preds:
            continue
        val = spec.validation[k]
        names = [n for n in val.inputs if n in spec.physics.inputs] or list(val.inputs)
        figs[f"predictions_{k}.png"] = plot_validation_predictions(
            preds, val.y, {n: val.inputs[n] for n in names}, output_name=k
        )
    write_figures(folder, figs)
