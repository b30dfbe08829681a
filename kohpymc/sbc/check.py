"""The check: replicates as tasks, resumable, summarised (:func:`check_calibration`)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import xarray as xr

from kohpymc.config import StudySpec, load_study
from kohpymc.execution import run_tasks
from kohpymc.sbc import files
from kohpymc.sbc.replicates import (
    Fitter,
    Recipe,
    Replicate,
    build_fitter,
    build_simulator,
    cached_fitter,
    fit_replicate,
    remember,
    verify_swap,
)
from kohpymc.sbc.settings import CheckSettings, model_hash, replicate_seed, resolve, setup_hash
from kohpymc.sbc.summary import MAX_FLAGGED, coverage_table, prior_data_note, verdict

__all__ = ["CalibrationCheck", "check_calibration"]


def _fit_replicate_task(key: str, item: Any) -> Any:
    """:func:`fit_replicate` as a :func:`kohpymc.execution.run_tasks` task."""
    return fit_replicate(item)


def _unpack(outcome: Any) -> tuple[str, Any, Any, float]:
    if hasattr(outcome, "key"):
        return outcome.key, outcome.value, outcome.error, float(outcome.seconds)
    key, value, error, seconds = outcome
    return key, value, error, float(seconds)


@dataclass
class CalibrationCheck:
    """The result of :func:`check_calibration`.

    Attributes
    ----------
    settings : CheckSettings
    passed : bool
    verdict : str
        One line, ``"PASS: ..."`` or ``"FAIL: ..."``.
    table : pandas.DataFrame
        Per parameter: ``cover50``, ``cover90`` (with ``_se``), ``mean_rank`` (``/L``),
        ``chi2_p``, over the usable replicates.
    ranks : xarray.Dataset
        ``rank``, ``truth``, ``cover50``, ``cover90``, ``r_hat``, ``ess_bulk``,
        ``ess_tail`` over ``(replicate, parameter)``, ``thinned`` over ``(replicate,
        parameter, draw)``, ``seed`` and ``usable`` over ``replicate``.
    records : list of dict
        Every finished replicate's result.
    failures : dict index -> str
        Replicates whose fit raised.
    timings : dict
        Seconds: ``setup_compile`` (building and compiling the fitted model, when this run
        fitted replicates), ``replicate_mean``/``_median``/``s_total`` (each replicate's fit,
        reused ones as measured when they were fitted) and ``wall`` (this run).
    reused : int
        Replicates read back from an earlier run.
    files : list of Path
    """

    settings: CheckSettings
    passed: bool
    verdict: str
    table: pd.DataFrame
    ranks: xr.Dataset
    records: list[dict[str, Any]]
    failures: dict[int, str] = field(default_factory=dict)
    timings: dict[str, Any] = field(default_factory=dict)
    reused: int = 0
    files: list[Path] = field(default_factory=list)
    setup_hash: str = ""

    @property
    def flagged(self) -> list[dict[str, Any]]:
        """The finished replicates with sampler trouble (left out of the table)."""
        return [r for r in self.records if r["problems"]]


def check_calibration(
    study: str | Path | StudySpec,
    *,
    replicates: int | None = None,
    formulation: str | None = None,
    draws: int | None = None,
    tune: int | None = None,
    chains: int | None = None,
    seed: int | None = None,
    rank_draws: int | None = None,
    out_dir: str | Path | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    fresh: bool = False,
    progress: Callable[[str], None] | None = None,
) -> CalibrationCheck:
    """Simulation-based calibration of one formulation of a study (see the module docstring).

    Parameters
    ----------
    study : path or StudySpec
        The study file (or its :func:`~kohpymc.config.load_study` result).
    replicates : int, optional
        Number of simulated data sets (else ``[check] replicates``).
    formulation : str, optional
        Label of the formulation (else ``[check] formulation``, else ``"M0"``).
    draws, tune, chains, seed, rank_draws : int, optional
        Override ``[check]`` (which overrides ``[sampling]``); ``rank_draws`` is ``L``,
        the number of thinned posterior draws a rank is computed among (default 99).
    out_dir : path, optional
        Write the replicate files, ``table.md``/``.csv``, ``ranks.nc``, ``ranks.png``
        and ``check.json`` here; a rerun into the same folder reuses every replicate whose
        set-up hash and seed match.
    workers, scheduler :
        Run replicates on a Dask cluster of ``workers`` processes or at ``scheduler``.
    fresh : bool
        Recompute every replicate.
    progress : callable, optional
        Receives one line per finished replicate.

    Returns
    -------
    CalibrationCheck

    Examples
    --------
    >>> from kohpymc.examples import decay
    >>> check = check_calibration(decay.STUDY_FILE, replicates=4, draws=200, tune=200,
    ...                           chains=2, seed=1)  # doctest: +SKIP
    >>> check.table.loc["k", "cover90"] <= 1.0  # doctest: +SKIP
    True
    """
    started = time.perf_counter()
    spec = study if isinstance(study, StudySpec) else load_study(study)
    overrides = dict(
        replicates=replicates, formulation=formulation, draws=draws, tune=tune,
        chains=chains, seed=seed, rank_draws=rank_draws,
    )  # fmt: skip
    settings = resolve(spec, overrides)
    recipe = _recipe(spec, settings)
    out = None if out_dir is None else Path(out_dir)
    seeds = [replicate_seed(settings.seed, i) for i in range(settings.replicates)]
    done = {} if out is None or fresh else files.read_replicates(out, recipe.setup_hash, seeds)
    say = progress or (lambda _msg: None)
    if done:
        say(f"{len(done)} of {settings.replicates} replicates reused from {out}")
    timings: dict[str, Any] = {}
    todo = [i for i in range(settings.replicates) if i not in done]
    records: dict[int, Any] = dict(done)
    failures: dict[int, Any] = {}
    if todo:
        new, failures = _run_replicates(
            spec, settings, recipe, todo, seeds, out, workers, scheduler, say, timings
        )
        records.update(new)
    return _finish(spec, settings, recipe, records, failures, done, timings, started, out)


def _recipe(spec: StudySpec, settings: CheckSettings) -> Recipe:
    """The check's recipe: study file, settings and the hashes of set-up and model."""
    return Recipe(
        str(Path(spec.source).resolve()),
        settings,
        setup_hash(spec, settings),
        model_hash(spec, settings.formulation, settings.mode),
    )


def _run_replicates(
    spec: StudySpec,
    settings: CheckSettings,
    recipe: Recipe,
    todo: list[int],
    seeds: list[int],
    out: Path | None,
    workers: int,
    scheduler: str | None,
    say: Callable[[str], None],
    timings: dict[str, Any],
) -> tuple[dict[int, Any], dict[int, Any]]:
    """Compile once, fit the ``todo`` replicates (writing each to ``out``): results, errors."""
    records: dict[int, Any] = {}
    failures: dict[int, Any] = {}
    say(f"{settings.formulation}: composing and compiling the fitted model (once)")
    fitter = _prepare(spec, settings, recipe, timings)
    tasks = _tasks(spec, settings, recipe, fitter, todo, seeds)
    say(
        f"{settings.formulation}: compiled in {timings['setup_compile']:.1f} s; fitting "
        f"{len(todo)} replicate(s), {settings.chains} × {settings.draws} draws each"
    )
    for index, result, error in _collect(tasks, workers, scheduler, say, settings):
        if error is not None:
            failures[index] = error
            continue
        records[index] = result
        if out is not None:
            files.write_replicate(out, recipe.setup_hash, result)
    return records, failures


def _prepare(spec: StudySpec, settings: CheckSettings, recipe: Recipe, timings) -> Fitter:
    """Compile the fitted model once (checking that data can be swapped into it)."""
    cached = cached_fitter(recipe.model_hash)
    if cached is not None:  # an earlier check of the same model in this thread
        timings["setup_compile"] = 0.0
        return cached
    formulation = spec.formulations[settings.formulation]
    fitter = build_fitter(spec.physics, spec.calibration, formulation, settings.mode)
    verify_swap(fitter, spec.physics, spec.calibration, formulation)
    remember(recipe, fitter)
    timings["setup_compile"] = fitter.compile_seconds
    return fitter


def _tasks(spec, settings, recipe, fitter: Fitter, todo: list[int], seeds) -> dict[str, Any]:
    """Simulate every replicate still to do (cheap; one compiled draw function)."""
    formulation = spec.formulations[settings.formulation]
    wanted = sorted({var for var, _ in fitter.parameters.values()})
    simulate = build_simulator(spec, formulation, wanted)
    tasks = {}
    for index in todo:
        sim_seed = int(np.random.SeedSequence(seeds[index], spawn_key=(0,)).generate_state(1)[0])
        truth, y = simulate(sim_seed)
        tasks[str(index)] = Replicate(recipe, index, seeds[index], y, truth)
    return tasks


def _collect(tasks, workers, scheduler, say, settings: CheckSettings):
    """Run the tasks; yield ``(index, result, error message)`` as each finishes."""
    finished = flagged = 0
    for outcome in run_tasks(_fit_replicate_task, tasks, workers=workers, scheduler=scheduler):
        key, value, error, seconds = _unpack(outcome)
        finished += 1
        if error is not None:
            message = (
                f"{type(error).__name__}: {error}" if isinstance(error, BaseException) else error
            )
            say(f"replicate {key}: failed ({str(message).splitlines()[0]})")
            yield int(key), None, str(message)
            continue
        flagged += bool(value["problems"])
        say(
            f"replicate {key} done in {seconds:.1f} s ({finished}/{len(tasks)}; "
            f"{flagged} with sampler trouble)"
            + (f": {'; '.join(value['problems'])}" if value["problems"] else "")
        )
        yield int(key), value, None


def _finish(spec, settings, recipe, records, failures, done, timings, started, out):
    """Table, verdict, ranks dataset and (with ``out``) the files."""
    ordered = [records[i] for i in sorted(records)]
    if not ordered:
        raise RuntimeError(
            f"no replicate of {settings.formulation} finished: "
            + "; ".join(f"{i}: {m}" for i, m in sorted(failures.items())[:3])
        )
    usable = [r for r in ordered if not r["problems"]]
    names = list(ordered[0]["rank"])
    table = coverage_table(usable, names, settings.rank_draws)
    passed, line = verdict(table, len(ordered), len(ordered) - len(usable), settings.formulation)
    if len(ordered) - len(usable) > MAX_FLAGGED * len(ordered):
        note = prior_data_note(ordered, spec.calibration.y, spec.calibration.noise_sd)
        line += f"; {note}" if note else ""
    seconds = [float(r["seconds"]) for r in ordered]  # reused ones: when they were fitted
    timings["replicate_mean"] = statistics.fmean(seconds)
    timings["replicate_median"] = statistics.median(seconds)
    timings["replicates_total"] = sum(seconds)
    timings["wall"] = time.perf_counter() - started
    result = CalibrationCheck(
        settings, passed, line, table, files.ranks_dataset(ordered, names, settings),
        ordered, failures, timings, len(done), [], recipe.setup_hash,
    )  # fmt: skip
    if out is not None:
        files.write_check(out, result, spec.source)
    return result
