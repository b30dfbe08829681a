"""The ``[emulator]`` table of a study file and the emulated physics of a study.

::

    [emulator]
    runs = 200                  # initial design size
    design = "maximin-lhs"      # or "lhs", "sobol"
    sequential = 2              # rounds of runs added at posterior draws (0: none)
    # refine_at_data = 2        # rounds of runs added around the emulator's best fit
    #                           # while its check at the data fails (0: none)
    # refine_runs = 300         # most runs those rounds add (default: room for every
    #                           # round, each θ̂ and p + 1 θ around it at the data's rows)
    # refine_at_posterior = 1   # rounds of runs added at the posteriors of formulations
    #                           # where the emulator is unfit, then calibrated again
    # kernel = "matern52"       # or "se"
    # new_runs = 100            # runs added per round (default runs // 2)
    # tolerance = 0.1           # stop when posterior means move less (in posterior sds)
    # formulation = "M0"        # label of [formulations] the rounds calibrate with
    # covariance = "full"       # or "diagonal" (see Emulator.physics_model)
    # log_output = "auto"       # emulate ln y: true, false, or "auto" (positive runs
    #                           # spanning two decades or more)
    # seed = 0
    # functional = ["t"]        # a curve per run over these inputs: a FunctionalEmulator
    #                           # (kohpymc.emulator.functional_study; no refinement rounds)

With it, :func:`study_physics` replaces the study's physics by the emulator: simulator
runs are cached in ``<output>/emulator/runs/`` (a resumed or extended study reuses them),
the validation of the emulator goes to ``<output>/emulator/check.json`` and ``check.png``
(over the design, with the predicted posterior widening at the data) and
``check_at_data.json`` (one simulator run at the emulator's best fit to the data).  When
that check fails, up to ``refine_at_data`` rounds add runs around the best fit
(:func:`~kohpymc.emulator.refinement.refine_at_data`; no sampling), refit and check again;
``refine_at_data.json`` has every round's check, and the ``EmulatorWarning`` stays, saying
so, when the last check still fails.  These rounds come before the sequential ones, which
are skipped when the last check passed with a predicted move below ``tolerance``
(:func:`rounds_not_needed`; the reason in ``rounds.csv``); the
sequential rounds to ``rounds.csv``, the fitted hyperparameters to ``emulator.json`` and
every run (failures with their error) to ``runs.csv``. The rounds' final design goes to
``rounds.json`` (also after refinement rounds alone) with a key of the settings,
simulator, data (and, with sequential rounds, formulation and sampler settings): a rerun
with the same key refits the final emulator from the cached runs instead of running the
rounds again.  A multi-output study
(:func:`~kohpymc.multi_output.emulator.study_outputs_physics`) goes through the same
:func:`study_emulators`: one check at the data over all its outputs, refinement rounds whose
runs give every output, the same files.  Every file is written under a temporary name and
renamed.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.emulator.at_data import SINGLE, EmulatorsAtData
from kohpymc.emulator.checking import (
    EmulatorCheck,
    check_emulator,
    check_target_at_data,
    warn_at_data,
)
from kohpymc.emulator.design import DESIGNS
from kohpymc.emulator.gp import KERNELS, EmulatedPhysics, Emulator, EmulatorWarning
from kohpymc.emulator.posterior_rounds import PosteriorRounds, refine_at_posteriors
from kohpymc.emulator.refinement import Refinement, refine_emulators_at_data
from kohpymc.emulator.runs import run_design
from kohpymc.emulator.sequential import emulate, emulator_box, fit_emulator, sequential_design
from kohpymc.fingerprint import (
    data_fingerprint,
    digest,
    formulation_fingerprint,
    kohpymc_version,
    physics_fingerprint,
)
from kohpymc.physics import PhysicsModel
from kohpymc.study_files import write_atomic
from kohpymc.warning_filters import warn_user

__all__ = [
    "EmulatorSettings",
    "rounds_key",
    "rounds_not_needed",
    "study_emulators",
    "study_physics",
    "warn_if_extrapolating",
    "warn_recorded",
    "write_check",
    "write_check_at_data",
    "write_emulator",
    "write_settings",
]

#: the rounds' key and final design (a rerun with the same key skips them)
ROUNDS_RECORD = "rounds.json"
#: the refinement rounds at the data: each round's runs and check
REFINEMENT_RECORD = "refine_at_data.json"


@dataclass(frozen=True)
class EmulatorSettings:
    """The ``[emulator]`` table of a study file.

    Examples
    --------
    >>> settings = EmulatorSettings.from_table({"runs": 200, "sequential": 2})
    >>> settings.runs, settings.design, settings.sequential, settings.kernel
    (200, 'maximin-lhs', 2, 'matern52')
    >>> EmulatorSettings.from_table({"runs": 0})
    Traceback (most recent call last):
    ...
    KeyError: 'runs'
    must be an integer >= 2, got 0
    """

    runs: int = 100
    design: str = "maximin-lhs"
    sequential: int = 0
    kernel: str = "matern52"
    new_runs: int | None = None
    tolerance: float = 0.1
    formulation: str | None = None
    covariance: str = "full"
    log_output: bool | Literal["auto"] = "auto"
    seed: int = 0
    refine_at_data: int = 2
    refine_runs: int | None = None
    functional: tuple[str, ...] = ()
    refine_at_posterior: int = 1

    def design_options(self) -> dict[str, Any]:
        """The keywords of :func:`~kohpymc.emulator.emulate` these settings fix.

        Examples
        --------
        >>> EmulatorSettings(runs=50).design_options()["runs"]
        50
        """
        return {
            "runs": self.runs,
            "design": self.design,
            "kernel": self.kernel,
            "log_output": self.log_output,
            "seed": self.seed,
        }

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> EmulatorSettings:
        """Check a TOML table; a bad value raises ``KeyError(key)`` with ``.note``.

        The error's ``args[0]`` is the key at fault and ``__notes__`` say why (the
        caller adds the file name).
        """
        allowed = set(cls.__dataclass_fields__)
        unknown = sorted(set(table) - allowed)
        if unknown:
            raise _bad(unknown[0], f"unknown key(s) {unknown}; allowed: {sorted(allowed)}")
        values = dict(table)
        minimums = (
            ("runs", 2), ("sequential", 0), ("new_runs", 1), ("seed", 0),
            ("refine_at_data", 0), ("refine_runs", 1), ("refine_at_posterior", 0),
        )  # fmt: skip
        for key, minimum in minimums:
            if key in values:
                v = values[key]
                if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
                    raise _bad(key, f"must be an integer >= {minimum}, got {v!r}")
        choices = {"design": DESIGNS, "kernel": KERNELS, "covariance": ("full", "diagonal")}
        for key, options in choices.items():
            if key in values and values[key] not in options:
                raise _bad(key, f"must be one of {list(options)}, got {values[key]!r}")
        if "tolerance" in values:
            tol = values["tolerance"]
            if isinstance(tol, bool) or not isinstance(tol, int | float) or not tol > 0:
                raise _bad("tolerance", f"must be a number > 0, got {tol!r}")
            values["tolerance"] = float(tol)
        if "log_output" in values and values["log_output"] not in (True, False, "auto"):
            raise _bad("log_output", f'must be true, false or "auto", got {values["log_output"]!r}')
        if "formulation" in values and not isinstance(values["formulation"], str):
            raise _bad("formulation", "must be a formulation label (a string)")
        if "functional" in values:
            values["functional"] = _functional_inputs(values)
            values["refine_at_data"] = 0  # no refinement rounds for curves
            values["refine_at_posterior"] = 0
        return cls(**values)


def _functional_inputs(values: Mapping[str, Any]) -> tuple[str, ...]:
    """``functional``: a non-empty list of distinct names; no refinement keys beside it."""
    names = values["functional"]
    if (
        not isinstance(names, list)
        or not names
        or not all(isinstance(k, str) and k for k in names)
        or len(set(names)) < len(names)
    ):
        raise _bad(
            "functional",
            "must be a list of the distinct physics inputs a run's curve spans "
            f'(e.g. ["t"]), got {names!r}',
        )
    for key in ("refine_at_data", "refine_runs", "refine_at_posterior"):
        if values.get(key):
            raise _bad(
                key,
                f"is {values[key]!r}, but refinement rounds (at the data or at the "
                "posteriors) are for the scalar emulator; a functional one (functional = "
                "[...]) adds runs by sequential rounds only (sequential = N)",
            )
    return tuple(names)


def _bad(key: str, why: str) -> KeyError:
    err = KeyError(key)
    err.add_note(why)
    return err


def study_physics(
    settings: EmulatorSettings,
    physics: PhysicsModel,
    calibration: CalibrationData,
    out_dir: str | Path,
    *,
    formulations: Mapping[str, Discrepancy] | None = None,
    sampling: Mapping[str, Any] | None = None,
    workers: int = 1,
    scheduler: Any = None,
    validation: CalibrationData | None = None,
) -> EmulatedPhysics:
    """Build (or rebuild from cached runs) a study's emulator; return it as physics.

    Parameters
    ----------
    settings : EmulatorSettings
        The ``[emulator]`` table.
    physics, calibration :
        The study's simulator and calibration data.
    out_dir : path
        The study's output folder (``emulator/`` is written inside).
    formulations : mapping, optional
        The study's formulations; ``settings.formulation`` picks the one the
        sequential rounds calibrate with (default M0, no discrepancy).
    sampling : mapping, optional
        Sampler settings of the rounds' calibrations (``draws``, ``chains``, ...).
    workers, scheduler :
        Where the simulator runs go.
    validation : CalibrationData, optional
        The study's validation data: an ``EmulatorWarning`` names every input whose
        validation values lie outside the design box (predictions there extrapolate),
        and the refinement rounds run each θ at its rows too
        (:meth:`~kohpymc.emulator.at_data.EmulatorsAtData.also_at`).

    Returns
    -------
    EmulatedPhysics

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import beam
    >>> physics = study_physics(EmulatorSettings(runs=30, refine_at_data=0),
    ...                         beam.physics_model(), beam.generate_data(seed=1),
    ...                         tempfile.mkdtemp())
    >>> physics.emulator.n_runs
    30
    """
    if settings.functional:
        from kohpymc.emulator.functional_study import study_functional_physics

        return study_functional_physics(
            settings, physics, calibration, out_dir, formulations=formulations,
            sampling=sampling, workers=workers, scheduler=scheduler, validation=validation,
        )  # fmt: skip
    folder = Path(out_dir) / "emulator"
    key = _study_key(settings, physics, calibration, formulations, sampling, validation)

    def first() -> EmulatorsAtData:
        options = settings.design_options()
        emulator = emulate(
            physics, calibration, cache=folder / "runs", workers=workers, scheduler=scheduler,
            **options,
        )  # fmt: skip
        return EmulatorsAtData.of(emulator, calibration).also_at(validation)

    def sequential(target: EmulatorsAtData, last_check: Any) -> EmulatorsAtData:
        reason = rounds_not_needed(settings, last_check)
        if reason:
            _write_skipped_rounds(folder, target.first, reason)
            return target
        emulator = _sequential_rounds(
            settings, physics, calibration, target.first, folder, formulations=formulations,
            sampling=sampling, workers=workers, scheduler=scheduler,
        )  # fmt: skip
        return EmulatorsAtData.of(emulator, calibration)

    emulator = study_emulators(
        settings, physics, folder, first, key=key,
        more_rounds=sequential if settings.sequential > 0 else None,
        workers=workers, scheduler=scheduler,
    )[SINGLE]  # fmt: skip
    write_settings(folder, settings)
    write_emulator(folder, emulator)
    if validation is not None:
        warn_if_extrapolating(emulator, validation, "validation")
    emulated = emulator.physics_model(covariance=settings.covariance)  # type: ignore[arg-type]
    emulated.runs_cache = folder / "runs"  # the checks at each posterior run into the cache
    return emulated


def _study_key(
    settings: EmulatorSettings,
    physics: PhysicsModel,
    calibration: CalibrationData,
    formulations: Mapping[str, Discrepancy] | None,
    sampling: Mapping[str, Any] | None,
    validation: CalibrationData | None,
) -> str:
    """The study's :func:`rounds_key`, or empty when no rounds can add runs."""
    rounds = (settings.sequential, settings.refine_at_data, settings.refine_at_posterior)
    if not any(rounds):
        return ""
    return rounds_key(settings, physics, calibration, formulations, sampling, validation)


def posterior_round(
    settings: EmulatorSettings,
    physics: EmulatedPhysics,
    calibration: CalibrationData,
    unfit: Mapping[str, Any],
    out_dir: str | Path,
    *,
    formulations: Mapping[str, Discrepancy] | None = None,
    sampling: Mapping[str, Any] | None = None,
    workers: int = 1,
    scheduler: Any = None,
    validation: CalibrationData | None = None,
) -> tuple[EmulatedPhysics, PosteriorRounds] | None:
    """One round at the posteriors where the emulator is unfit: the refitted emulator.

    ``unfit``: label -> the formulation's InferenceData (its ``physics_problems`` not
    empty).  None when the study's ``refine_at_posterior`` rounds have all run (as
    recorded in ``refine_at_posterior.json`` under the study's key, so a rerun adds
    none).  Else runs at each posterior
    (:func:`~kohpymc.emulator.posterior_rounds.refine_at_posteriors`, ``new_runs`` per
    posterior), the emulator refitted; ``rounds.json`` then holds its design (a rerun
    restores it), and ``emulator.json``, ``runs.csv`` and the round's record are written.
    Returns the refitted emulator as physics and the record (the caller adds what the
    next calibrations showed and writes it again).  Other arguments as for
    :func:`study_physics`.
    """
    from kohpymc.calibration import physics_problems

    folder = Path(out_dir) / "emulator"
    source = physics.emulator.physics
    key = _study_key(settings, source, calibration, formulations, sampling, validation)
    record = PosteriorRounds.read(folder, key)
    if not key or record.done >= settings.refine_at_posterior:
        return None
    emulator, thetas = refine_at_posteriors(
        physics.emulator, calibration, unfit, validation=validation, new_runs=settings.new_runs,
        cache=folder / "runs", seed=settings.seed + record.done, workers=workers,
        scheduler=scheduler,
    )  # fmt: skip
    _write_rounds_record(folder, key, {SINGLE: emulator})
    # fitted again from the record, as a rerun will restore it: the same posteriors reused
    record_file = read_rounds_record(folder, key) or {}
    emulator = _refitted(record_file, folder, settings, source, workers, scheduler)[SINGLE]
    write_emulator(folder, emulator)
    record.rounds.append(
        {
            "unfit": {label: physics_problems(idata) for label, idata in unfit.items()},
            "thetas": thetas.to_dict(orient="records"),
            "runs_added": int(emulator.n_runs - physics.emulator.n_runs),
            "runs": int(emulator.n_runs),
        }
    )
    record.write(folder)
    refined = emulator.physics_model(covariance=settings.covariance)  # type: ignore[arg-type]
    refined.runs_cache = folder / "runs"
    return refined, record


def study_emulators(
    settings: EmulatorSettings,
    simulator: Any,
    folder: Path,
    first: Callable[[], EmulatorsAtData],
    *,
    key: str = "",
    more_rounds: Callable[[EmulatorsAtData, Any], EmulatorsAtData] | None = None,
    workers: int = 1,
    scheduler: Any = None,
) -> dict[str, Emulator]:
    """A study's emulators (one per output): restored from an earlier run, or built.

    With a record of earlier rounds under ``key`` (``rounds.json``), the final design
    is read from the run cache and every output's emulator refitted to it (no
    simulator call).  Else ``first()`` builds them (design, runs, fits), their checks
    over the design and at the data are written, the refinement rounds at the data run
    (``refine_at_data``), then ``more_rounds`` (the sequential rounds of one output),
    and with a ``key`` the final design is recorded.

    Parameters
    ----------
    settings : EmulatorSettings
    simulator : PhysicsModel or MultiOutputPhysics
        What runs.
    folder : path
        ``<output>/emulator``.
    first : callable
        Builds the first emulators (with their data).
    key : str
        What the rounds depend on (empty: nothing recorded or restored).
    more_rounds : callable, optional
        Rounds after the refinement (the sequential ones), given the emulators and the
        last check at the data.
    workers, scheduler :
        Where the simulator runs go.

    Returns
    -------
    dict of str to Emulator
        Output -> emulator (one output: ``"output"``).

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import beam
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> folder = Path(tempfile.mkdtemp())
    >>> first = lambda: EmulatorsAtData.of(emulate(physics, data, runs=30), data)
    >>> settings = EmulatorSettings(runs=30, refine_at_data=0)
    >>> study_emulators(settings, physics, folder, first)["output"].n_runs
    30
    """
    folder.mkdir(parents=True, exist_ok=True)
    emulators = _restored_rounds(folder, key, settings, simulator, workers, scheduler)
    if emulators is not None:
        return emulators
    target = first()
    at_data, design = _write_checks(
        folder, target, warn=settings.refine_at_data == 0, workers=workers, scheduler=scheduler
    )
    target, last_check = _refined(settings, target, at_data, design, folder, workers, scheduler)
    if more_rounds is not None:
        target = more_rounds(target, last_check)
    if key:
        _write_rounds_record(folder, key, target.emulators)
    return target.emulators


#: an emulator input whose fitted length scale exceeds this many box widths is one the
#: output does not depend on (for extrapolation warnings)
IRRELEVANT_LENGTHSCALE = 10.0


def warn_if_extrapolating(emulator: Emulator, data: CalibrationData, what: str) -> None:
    """``EmulatorWarning`` naming the inputs of ``data`` beyond the design box.

    An input counts when the data leave the box by more than 1 % of its width.  An
    input the fit found the output not to depend on (length scale above
    :data:`IRRELEVANT_LENGTHSCALE` box widths: a recorded batch number got 91–848) counts
    only beyond 5 % of its length scale, where the kernel's correlation has dropped by
    ~0.2 %: closer, no prediction changes in a way that matters.  ``what`` names the
    data in the message (``"validation"``).

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> data = beam.generate_data(seed=1)
    >>> warn_if_extrapolating(emulate(beam.physics_model(), data, runs=10), data, "calibration")
    """
    outside = []
    for j, name in enumerate(emulator.columns[: emulator.n_inputs]):
        values = np.asarray(data.inputs[name], dtype=float)
        ends = np.array([values.min(), values.max()])
        with np.errstate(divide="ignore", invalid="ignore"):
            scaled = np.log(np.abs(ends)) if emulator.log_columns[j] else ends
        unit = (scaled - emulator.lower[j]) / emulator.width[j]
        beyond = max(-unit.min(), unit.max() - 1.0)
        lengthscale = float(emulator.hyper.lengthscales[j])
        if beyond > (0.05 * lengthscale if lengthscale > IRRELEVANT_LENGTHSCALE else 0.01):
            box = emulator.runs.points[name]
            outside.append(
                f"{name} in [{ends[0]:.4g}, {ends[1]:.4g}] (runs cover "
                f"[{box.min():.4g}, {box.max():.4g}])"
            )
    if outside:
        warn_user(
            f"emulator of {emulator.physics.name!r}: the {what} inputs leave its design box, "
            f"{'; '.join(outside)}: predictions there extrapolate the emulator",
            EmulatorWarning,
        )


def _refined(
    settings: EmulatorSettings,
    target: EmulatorsAtData,
    at_data: Any,
    design: list[str],
    folder: Path,
    workers: int,
    scheduler: Any,
) -> tuple[EmulatorsAtData, Any]:
    """The refinement rounds at the data (if any and if the check failed); files and warning.

    ``refine_at_data.json`` records every round; with runs added, the checks over the
    design (``check.json``) and ``check_at_data.json`` are rewritten for the refitted
    emulators.  ``design``: the problems of the first emulators' checks over the design,
    named in the warning when the last check at the data fails.  Returns the emulators
    and the last check at the data.
    """
    if settings.refine_at_data == 0:
        return target, at_data
    result = refine_emulators_at_data(
        target,
        rounds=settings.refine_at_data,
        new_runs=settings.new_runs,
        max_runs=settings.refine_runs,
        first=at_data,
        cache=folder / "runs",
        seed=settings.seed,
        workers=workers,
        scheduler=scheduler,
    )
    _write_json(folder / REFINEMENT_RECORD, result.to_dict())
    if result.added:
        design = _write_design_checks(folder, result.target)
        _write_json(folder / "check_at_data.json", result.checks[-1].to_dict())
    warn_at_data(
        result.target, result.checks[-1], _refinement_advice(settings, result),
        design_problems=design,
    )  # fmt: skip
    return result.target, result.checks[-1]


def rounds_not_needed(settings: EmulatorSettings, check: Any) -> str:
    """Why the sequential rounds would be idle (empty: they are not).

    The rounds stop once the posterior moves less than ``tolerance`` posterior sds.  When
    the last check at the data passed (after any refinement rounds) and predicts that the
    emulator's error moves the least-squares θ by less than ``tolerance`` posterior sds
    for every parameter, the first round's posterior would already be the last: on the
    Langmuir isotherm (``runs = 40``, one refinement round to 112 runs, check passed) the
    round added 54 runs and two calibrations, and the posterior through the refined
    emulator was already within 0.02 direct sds of the direct one (the round moved it
    0.07 sds).  A lower ``tolerance`` runs them.

    Examples
    --------
    >>> empty = np.empty(0)
    >>> check = EmulatorCheck("at the calibration data", empty, empty, empty,
    ...                       shift={"E": 0.03})
    >>> rounds_not_needed(EmulatorSettings(sequential=2), check)[:36]
    'the check at the data passed and its'
    >>> rounds_not_needed(EmulatorSettings(sequential=2, tolerance=0.01), check)
    ''
    """
    shift = getattr(check, "shift", None)
    if not check.fit or not shift:
        return ""
    largest = max(abs(v) for v in shift.values())
    if largest >= settings.tolerance:
        return ""
    return (
        f"the check at the data passed and its emulator error moves the least-squares θ by "
        f"at most {largest:.2g} posterior sds (< tolerance = {settings.tolerance}): the "
        "rounds' posterior would not move (lower tolerance to run them)"
    )


def _write_skipped_rounds(folder: Path, emulator: Emulator, reason: str) -> None:
    """``rounds.csv`` of rounds not run: the emulator's runs and the reason."""
    table = pd.DataFrame(
        {"round": [0], "runs": [emulator.n_runs], "shift_sd": [float("nan")], "skipped": [reason]}
    ).set_index("round")
    write_atomic(folder / "rounds.csv", lambda tmp: table.to_csv(tmp))


def _refinement_advice(settings: EmulatorSettings, result: Refinement) -> str:
    """What the warning after failed refinement rounds says they did and what to try."""
    cap = "" if settings.refine_runs is None else f", refine_runs = {settings.refine_runs}"
    return (
        f"still so after {len(result.added)} refinement round(s) that added "
        f"{sum(result.added)} runs around the best fit ([emulator] refine_at_data = "
        f"{settings.refine_at_data}{cap}; stopped: {result.stopped}); raise them, or "
        "runs, or use sequential rounds"
    )


def rounds_key(
    settings: EmulatorSettings,
    physics: Any,
    calibration: Any,
    formulations: Mapping[str, Discrepancy] | None = None,
    sampling: Mapping[str, Any] | None = None,
    validation: Any = None,
) -> str:
    """What the rounds' result depends on: settings, simulator, data (sequential: sampler).

    The key of ``rounds.json`` (:func:`study_emulators`).  ``validation``: the data whose
    rows the refinement rounds also run at (none: the key of a study without them).

    Refinement rounds alone do not sample, so the formulation and the sampler settings
    enter the key only with sequential rounds.  A simulator with several outputs (and
    their data) enters output by output.
    """
    outputs = tuple(getattr(physics, "outputs", ()))
    table = asdict(settings)
    if not settings.functional:  # keys recorded before the field existed stay valid
        del table["functional"]
    parts: dict[str, Any] = {
        "settings": table,
        "physics": (
            {k: physics_fingerprint(physics.output(k)) for k in outputs}
            if outputs
            else physics_fingerprint(physics)
        ),
        "data": (
            {k: data_fingerprint(calibration[k]) for k in calibration.outputs}
            if outputs
            else data_fingerprint(calibration)
        ),
        "version": kohpymc_version(),
    }
    if validation is not None:
        parts["validation"] = (
            {k: data_fingerprint(validation[k]) for k in validation.outputs}
            if outputs
            else data_fingerprint(validation)
        )
    if settings.sequential > 0:
        parts["formulation"] = formulation_fingerprint(_round_formulation(settings, formulations))
        parts["sampling"] = _calibrate_settings(sampling or {})
    return digest(parts)


def _write_rounds_record(folder: Path, key: str, emulators: Mapping[str, Emulator]) -> None:
    """``rounds.json``: the key and the final design, so a rerun refits without the rounds.

    Every output's emulator has the same runs and box; each its own output scale.
    """
    first = next(iter(emulators.values()))
    runs = first.runs
    columns = [*runs.inputs, *runs.parameters]
    record = {
        "key": key,
        "columns": columns,
        "design": runs.points[columns].to_numpy(dtype=float).tolist(),
        "box": emulator_box(first),
        "log_output": {k: em.log_output for k, em in emulators.items()},
    }
    text = json.dumps(record)
    write_atomic(folder / ROUNDS_RECORD, lambda tmp: tmp.write_text(text))


def read_rounds_record(folder: Path, key: str) -> dict[str, Any] | None:
    """``rounds.json`` of ``folder`` when it was written under ``key``, else None.

    None also without rounds (empty ``key``) and for a missing or unreadable file (the
    rounds then run again; their simulator runs still come from the cache).

    Examples
    --------
    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> _write_json(folder / ROUNDS_RECORD, {"key": "a", "design": []})
    >>> read_rounds_record(folder, "a")["design"], read_rounds_record(folder, "b")
    ([], None)
    """
    path = folder / ROUNDS_RECORD
    if not key or not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("key") != key:
        return None
    return record


def _restored_rounds(
    folder: Path,
    key: str,
    settings: EmulatorSettings,
    simulator: Any,
    workers: int,
    scheduler: Any,
) -> dict[str, Emulator] | None:
    """The final emulators of earlier rounds with the same ``key``, refitted from the cache.

    None without rounds (empty ``key``), without a record, or when the record's key
    differs (then the rounds run again; their simulator runs still come from the cache).
    A failed last check at the data (in ``check_at_data.json``) warns again.
    """
    record = read_rounds_record(folder, key)
    if record is None:
        return None
    emulators = _refitted(record, folder, settings, simulator, workers, scheduler)
    warn_recorded(folder, EmulatorsAtData(simulator, emulators, {}))
    return emulators


def _refitted(
    record: Mapping[str, Any],
    folder: Path,
    settings: EmulatorSettings,
    simulator: Any,
    workers: int,
    scheduler: Any,
) -> dict[str, Emulator]:
    """Output -> its emulator fitted to the design of a ``rounds.json`` record (cached runs)."""
    design = pd.DataFrame(record["design"], columns=record["columns"])
    runs = run_design(
        simulator, design, cache=folder / "runs", workers=workers, scheduler=scheduler
    )
    box = {k: (float(lo), float(hi)) for k, (lo, hi) in record["box"].items()}
    outputs = tuple(getattr(simulator, "outputs", ()))
    models = {k: simulator.output(k) for k in outputs} if outputs else {SINGLE: simulator}
    scales = record.get("log_output", settings.log_output)
    emulators = {
        k: fit_emulator(
            EmulatorsAtData.output_runs(runs, k),
            model,
            box=box,
            kernel=settings.kernel,
            seed=settings.seed,
            log_output=scales.get(k, settings.log_output) if isinstance(scales, dict) else scales,
        )  # fmt: skip
        for k, model in models.items()
    }
    return emulators


def warn_recorded(folder: Path, target: EmulatorsAtData) -> bool:
    """The warning of a failed check at the data recorded when the rounds ran.

    Returns whether ``check_at_data.json`` was there to read.
    """
    try:
        problems = json.loads((folder / "check_at_data.json").read_text())["problems"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    if problems:
        empty = np.empty(0)
        recorded = EmulatorCheck("at the calibration data", empty, empty, empty, problems=problems)
        warn_at_data(target, recorded, "(recorded in check_at_data.json when the rounds ran)")
    return True


def _round_formulation(
    settings: EmulatorSettings, formulations: Mapping[str, Discrepancy] | None
) -> Discrepancy | None:
    """The formulation the sequential rounds calibrate with (``None``: M0)."""
    if settings.formulation is None:
        return None
    if formulations is None or settings.formulation not in formulations:
        raise KeyError(
            f"[emulator] formulation {settings.formulation!r} is not one of the "
            f"study's formulations {sorted(formulations or {})}"
        )
    return formulations[settings.formulation]


def _sequential_rounds(
    settings: EmulatorSettings,
    physics: PhysicsModel,
    calibration: CalibrationData,
    emulator: Emulator,
    folder: Path,
    *,
    formulations: Mapping[str, Discrepancy] | None,
    sampling: Mapping[str, Any] | None,
    workers: int,
    scheduler: Any,
) -> Emulator:
    """Run the sequential rounds; write their table and the new check; the last emulator."""
    emulator = run_rounds(
        settings, physics, calibration, emulator, folder, formulations=formulations,
        sampling=sampling, workers=workers, scheduler=scheduler,
    )  # fmt: skip
    target = EmulatorsAtData.of(emulator, calibration)
    _write_checks(folder, target, workers=workers, scheduler=scheduler)
    return emulator


def run_rounds(
    settings: EmulatorSettings,
    physics: PhysicsModel,
    calibration: CalibrationData,
    emulator: Any,
    folder: Path,
    *,
    formulations: Mapping[str, Discrepancy] | None,
    sampling: Mapping[str, Any] | None,
    workers: int = 1,
    scheduler: Any = None,
) -> Any:
    """:func:`sequential_design` with the settings' rounds; ``rounds.csv``; the last emulator.

    ``emulator`` is an :class:`Emulator` or a ``FunctionalEmulator``; new runs are cached
    in ``folder/runs``.
    """
    result = sequential_design(
        physics,
        calibration,
        _round_formulation(settings, formulations),
        emulator=emulator,
        new_runs=settings.new_runs,
        rounds=settings.sequential,
        tolerance=settings.tolerance,
        cache=folder / "runs",
        seed=settings.seed,
        workers=workers,
        scheduler=scheduler,
        **_calibrate_settings(sampling or {}),
    )
    table = result.table()
    write_atomic(folder / "rounds.csv", lambda tmp: table.to_csv(tmp))
    return result.emulator


def _write_checks(
    folder: Path,
    target: EmulatorsAtData,
    *,
    warn: bool = True,
    workers: int = 1,
    scheduler: Any = None,
) -> tuple[Any, list[str]]:
    """``check.json``/``.png`` over the design, and ``check_at_data.json`` at the data.

    The second runs the simulator once, at the emulators' best fit to the calibration
    rows (cached in ``folder/runs`` like the design), since leave-one-out over the prior
    box can pass an emulator that is many noise sds off where the data are.  Returns it
    and the problems over the design (:func:`_write_design_checks`).
    """
    design = _write_design_checks(folder, target)
    at_data = write_check_at_data(
        folder, target, design, warn=warn, workers=workers, scheduler=scheduler
    )
    return at_data, design


def write_check_at_data(
    folder: Path,
    target: EmulatorsAtData,
    design_problems: list[str],
    *,
    warn: bool = True,
    advice: str | None = None,
    workers: int = 1,
    scheduler: Any = None,
) -> Any:
    """``check_at_data.json``: the check at the data (simulator run cached in ``folder/runs``).

    With ``warn``, its :func:`~kohpymc.emulator.checking.warn_at_data` when it fails,
    naming ``design_problems`` (those of the check over the design, written but not
    warned) and ``advice`` (default: that of the scalar emulator).  Returns the check.
    """
    at_data = check_target_at_data(
        target, cache=folder / "runs", workers=workers, scheduler=scheduler
    )
    if warn:
        extra = {} if advice is None else {"advice": advice}
        warn_at_data(target, at_data, design_problems=design_problems, **extra)
    _write_json(folder / "check_at_data.json", at_data.to_dict())
    return at_data


def _write_design_checks(folder: Path, target: EmulatorsAtData) -> list[str]:
    """Each output's :func:`check_emulator` (with its data's predicted widening); its problems.

    One output: ``folder/check.json``; several: ``folder/<output>/check.json``.  Written,
    not warned: whether an emulator is fit for *this* calibration is the check at the
    data's verdict, and leave-one-out over the whole design can fail far from the data
    (an isotherm study warned of a design-wide misfit although the emulator matched the
    simulator at the data).  The problems returned join that check's warning when it
    fails (:func:`~kohpymc.emulator.checking.warn_at_data`).
    """
    problems: list[str] = []
    for k, emulator in target.emulators.items():
        part = folder if target.single else folder / k
        part.mkdir(parents=True, exist_ok=True)
        check = check_emulator(emulator, data=target.data.get(k), warn=False)
        write_check(part, check)
        problems += [p if target.single else f"{k}: {p}" for p in check.problems]
    return problems


def _calibrate_settings(sampling: Mapping[str, Any]) -> dict[str, Any]:
    keys = {"draws", "tune", "chains", "target_accept", "sampler", "mode", "reparameterize"}
    out = {k: v for k, v in sampling.items() if k in keys}
    if "random_seed" in sampling:
        out["random_seed"] = sampling["random_seed"]
    out["warn"] = False
    return out


def write_settings(folder: Path, settings: EmulatorSettings) -> None:
    """``settings.json``: the ``[emulator]`` table the emulator was built with.

    Examples
    --------
    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> write_settings(folder, EmulatorSettings(runs=30))
    >>> json.loads((folder / "settings.json").read_text())["runs"]
    30
    """
    _write_json(folder / "settings.json", asdict(settings))


def write_emulator(folder: Path, emulator: Any) -> None:
    """``emulator.json`` (hyperparameters) and ``runs.csv`` (every run, failures too).

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import beam
    >>> folder = Path(tempfile.mkdtemp())
    >>> write_emulator(folder, emulate(beam.physics_model(), beam.generate_data(seed=1),
    ...                                runs=10))
    >>> sorted(p.name for p in folder.iterdir())
    ['emulator.json', 'runs.csv']
    """
    h = emulator.hyper
    record = {
        "emulator": repr(emulator),
        "kernel": emulator.kernel,
        "columns": list(emulator.columns),
        "lengthscales_unit_box": [float(v) for v in h.lengthscales],
        "amplitude": h.amplitude,
        "nugget": h.nugget,
        "log_posterior": h.log_posterior,
        "runs": emulator.n_runs,
        "failed_runs": int(len(emulator.runs.failed)),
    }
    _write_json(folder / "emulator.json", record)
    runs = emulator.runs
    table = runs.points.assign(error="")
    if len(runs.failed):
        table = pd.concat([table, runs.failed.assign(output=float("nan"))], ignore_index=True)
    write_atomic(folder / "runs.csv", lambda tmp: table.to_csv(tmp, index=False))


def write_check(folder: Path, check: Any) -> None:
    """``check.json`` (the scores of :func:`check_emulator`) and ``check.png`` (its figure).

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import beam
    >>> folder = Path(tempfile.mkdtemp())
    >>> em = emulate(beam.physics_model(), beam.generate_data(seed=1), runs=10)
    >>> write_check(folder, check_emulator(em, warn=False))
    >>> sorted(p.name for p in folder.iterdir())
    ['check.json', 'check.png']
    """
    _write_json(folder / "check.json", check.to_dict())
    import matplotlib.pyplot as plt

    fig = check.figure()
    write_atomic(folder / "check.png", lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)


def _write_json(path: Path, record: Any) -> None:
    """``record`` as indented JSON at ``path``, written under a temporary name and renamed."""
    text = json.dumps(record, indent=1)
    write_atomic(path, lambda tmp: tmp.write_text(text))
