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
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import arviz as az
import pandas as pd

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
from kohpymc.multi_output.model import compose_multi_output_model
from kohpymc.multi_output.reliability import OutputReliability, output_reliability
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
    """

    calibrations: dict[str, MultiOutputCalibration]
    reliabilities: dict[str, OutputReliability]
    failures: dict[str, str] = field(default_factory=dict)
    reused: list[str] = field(default_factory=list)
    predictions: dict[str, dict[str, az.InferenceData]] = field(default_factory=dict)

    @property
    def table(self) -> pd.DataFrame:
        """μ_r per (formulation, output) and combined, θ means/sds and sampler problems."""
        frames = []
        for label, rel in self.reliabilities.items():
            frame = rel.table[["n", "tolerance", "mu_r", "mu_r_mcse"]].copy()
            post = self.calibrations[label].posterior
            for name in self.calibrations[label].physics.parameter_names:
                frame[f"{name} mean"] = float(post[name].mean())
                frame[f"{name} sd"] = float(post[name].std())
            frame["sampler_problems"] = "; ".join(self.calibrations[label].problems) or "none"
            frames.append(frame.assign(formulation=label).reset_index())
        if not frames:
            raise ValueError(f"no formulation finished; failures: {self.failures}")
        return pd.concat(frames).set_index(["formulation", "output"])


def run_multi_output_study(
    spec: MultiOutputStudySpec,
    *,
    out_dir: str | os.PathLike[str] | None = None,
    fresh: bool = False,
    figures: bool = True,
    progress: Callable[[str], None] | None = None,
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
    **overrides :
        Replace sampler settings of the file (e.g. ``draws=300``).

    Returns
    -------
    MultiOutputStudyResult

    Examples
    --------
    >>> result = run_multi_output_study(spec, draws=300, tune=300)  # doctest: +SKIP
    >>> result.table.loc["M0"].index.tolist()  # doctest: +SKIP
    ['u', 'strain', 'combined']
    """
    settings = {**spec.sampling, **overrides}
    say = progress or (lambda message: None)
    folder = None if out_dir is None else StudyFolder(out_dir, fresh=fresh)
    result = MultiOutputStudyResult({}, {})
    n = len(spec.formulations)
    for i, (label, formulation) in enumerate(spec.formulations.items(), 1):
        start = time.perf_counter()
        try:
            _run_formulation(spec, label, formulation, settings, folder, result)
        except Exception as err:  # noqa: BLE001 - reported, the study goes on
            result.failures[label] = f"{type(err).__name__}: {err}"
            if folder is not None:
                folder.record(label, status="failed", error=result.failures[label])
            say(f"[{i}/{n}] {label}: failed: {result.failures[label]}")
            continue
        how = "reused" if label in result.reused else "done"
        say(f"[{i}/{n}] {label}: {how} in {time.perf_counter() - start:.1f} s")
    if folder is not None:
        _write_study_files(folder, result, spec, figures)
    return result


def _run_formulation(
    spec: MultiOutputStudySpec,
    label: str,
    formulation: Any,
    settings: dict[str, Any],
    folder: StudyFolder | None,
    result: MultiOutputStudyResult,
) -> None:
    """Calibrate (or reuse) one formulation, save it, and score it on the validation data."""
    seed = settings.get("random_seed")
    fingerprint = calibration_hash(spec, label, formulation, settings)
    cal = None
    if folder is not None:
        cal = _reusable(spec, folder, label, formulation, fingerprint, settings)
    if cal is not None:
        result.reused.append(label)
    else:
        cal = calibrate_outputs(
            spec.physics,
            spec.calibration,
            formulation,
            **{**settings, "random_seed": derived_seed(seed, label, 0)},
        )
        if folder is not None:
            _save(folder, label, cal, fingerprint)
    result.calibrations[label] = cal
    predictions = {
        k: predict_output(cal, k, spec.validation[k], random_seed=derived_seed(seed, label, 1))
        for k in spec.validation.outputs
        if k in cal.outputs
    }
    result.predictions[label] = predictions
    result.reliabilities[label] = output_reliability(
        cal, spec.validation, spec.tolerance, predictions=predictions
    )
    if folder is not None:
        status = "reused" if label in result.reused else "done"
        folder.record(label, status=status, file=f"{label}.nc", sampler_problems=cal.problems)


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
    spec: MultiOutputStudySpec,
    folder: StudyFolder,
    label: str,
    formulation: Any,
    fingerprint: str,
    settings: Mapping[str, Any],
) -> MultiOutputCalibration | None:
    """The formulation's calibration from an earlier file with the same fingerprint, or None."""
    earlier = folder.finished(label)
    if earlier is None or earlier.attrs.get(CALIBRATION_HASH) != fingerprint:
        return None
    idata = calibration_part(earlier)
    attrs = dict(earlier.attrs)
    problems = json.loads(attrs.pop("sampler_problems", "[]"))
    idata.attrs.update(attrs)
    noise_prior = settings.get("noise_sd_prior")
    built = compose_multi_output_model(
        spec.physics, spec.calibration, formulation, noise_sd_prior=noise_prior
    )
    return MultiOutputCalibration(
        spec.physics, spec.calibration, formulation, built, idata, problems, None, noise_prior
    )


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
    if result.reliabilities:
        write_table(folder, result.table)
        if figures:
            _write_figures(folder, result, spec)
    status = "failed" if not result.reliabilities else "done"
    folder.update(status=status, failures=result.failures, reused=result.reused)


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
