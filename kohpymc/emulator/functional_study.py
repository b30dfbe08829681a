"""A study's ``[emulator]`` with ``functional = [...]``: a curve per run, PCA emulated.

::

    [emulator]
    functional = ["t"]      # the physics inputs a run's curve spans
    runs = 40               # curves of the first design
    sequential = 2          # rounds of curves at posterior draws (0: none)

:func:`study_functional_physics` builds a
:class:`~kohpymc.emulator.functional.FunctionalEmulator` for
:func:`kohpymc.emulator.study.study_physics`: the **grid** is the distinct values of the
functional input(s) over the calibration and validation rows (so every data row is a
grid point), the **settings** the distinct values of the other (scalar) inputs there.
The first design is ``round(runs / m)`` θ by ``design`` over the prior box, each run at
every one of the ``m`` settings (:func:`~kohpymc.emulator.functional.at_settings`): one
simulator call per curve (:func:`~kohpymc.emulator.functional.run_curves`), cached in
``<output>/emulator/runs/``.  Two checks: on held-out curves, a fifth as many θ again
(at least 3; a Sobol design with seed + 1), at every setting, not used in the fit
(``check.json``/``check.png``, ``FunctionalEmulator.held_out_check``), and at the data
(``check_at_data.json``, :func:`~kohpymc.emulator.checking.check_at_data` through
:class:`~kohpymc.emulator.functional_at_data.CurvesAtData`): the simulator's curves at the
emulator's best fit to the calibration data, one per setting, against the emulator's
prediction there.  The second decides the ``EmulatorWarning``; the first, over the whole
prior box, is named in it when it fails too.  A rerun restoring the rounds' emulator
warns again from ``check_at_data.json`` instead of checking again.
``sequential = N`` runs :func:`~kohpymc.emulator.sequential.sequential_design` with the
functional emulator (``rounds.csv``); its final design goes to ``rounds.json`` under a
key of the settings, simulator, data and sampler settings, so a rerun refits the final
emulator from the cache without sampling.  ``emulator.json`` has the basis and the weight
GPs' hyperparameters, ``runs.csv`` every curve's design row (failures with their error),
``grid.csv`` the grid.  ``log_output = "auto"`` emulates ln y when every first curve is
positive and they span two decades or more.  No refinement rounds at the data.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.emulator.at_data import EmulatorsAtData
from kohpymc.emulator.design import log_scaled, space_filling_design
from kohpymc.emulator.functional import (
    FunctionalEmulatedPhysics,
    FunctionalEmulator,
    FunctionalRuns,
    at_settings,
    distinct_rows,
    run_curves,
)
from kohpymc.emulator.study import (
    ROUNDS_RECORD,
    EmulatorSettings,
    _write_json,
    read_rounds_record,
    rounds_key,
    run_rounds,
    warn_recorded,
    write_check,
    write_check_at_data,
    write_settings,
)
from kohpymc.fingerprint import data_fingerprint, digest
from kohpymc.initialization import prior_box
from kohpymc.physics import PhysicsModel
from kohpymc.study_files import write_atomic

__all__ = ["CurveStudy", "study_functional_physics", "write_functional_emulator"]

#: what the warning of a failed check at the data advises (no refinement rounds for curves)
ADVICE = "add curves ([emulator] runs or sequential rounds)"


@dataclass(frozen=True)
class CurveStudy:
    """What a functional study's runs are made of: simulator, grid, settings, θ box.

    Examples
    --------
    >>> from kohpymc.examples import decay
    >>> data = decay.generate_data(decay.CALIBRATION_TIMES, seed=1)
    >>> study = CurveStudy.of(EmulatorSettings(functional=("t",)), decay.physics_model(),
    ...                       data)
    >>> len(study.grid), study.points.shape, list(study.box)
    (21, (1, 0), ['A', 'k'])
    """

    settings: EmulatorSettings
    physics: PhysicsModel
    grid: pd.DataFrame
    scalar: tuple[str, ...]
    points: np.ndarray
    box: dict[str, tuple[float, float]]
    cache: Path | None = None
    workers: int = 1
    scheduler: Any = None

    @classmethod
    def of(
        cls,
        settings: EmulatorSettings,
        physics: PhysicsModel,
        *data: CalibrationData,
        cache: Path | None = None,
        workers: int = 1,
        scheduler: Any = None,
    ) -> CurveStudy:
        """The grid and settings of the data sets' rows, θ's prior box."""
        functional = list(settings.functional)
        scalar = tuple(k for k in physics.inputs if k not in functional)
        grid = pd.DataFrame(distinct_rows(functional, *data), columns=functional)
        return cls(
            settings, physics, grid, scalar, distinct_rows(scalar, *data), prior_box(physics),
            cache, workers, scheduler,
        )  # fmt: skip

    def design(self, n_curves: int, method: str, seed: int) -> pd.DataFrame:
        """About ``n_curves`` curves: ``round(n_curves / m)`` θ (at least 1) × the settings."""
        n_theta = max(1, round(n_curves / len(self.points)))
        thetas = space_filling_design(self.box, n_theta, method=method, seed=seed)  # type: ignore[arg-type]
        return at_settings(thetas, self.points, self.scalar, list(self.box))

    def run(self, design: pd.DataFrame) -> FunctionalRuns:
        """The simulator's curves at the design's rows (cached)."""
        return run_curves(
            self.physics, design, self.grid, cache=self.cache, workers=self.workers,
            scheduler=self.scheduler,
        )  # fmt: skip

    def fit(self, runs: FunctionalRuns, log_output: bool | None = None) -> FunctionalEmulator:
        """The emulator of ``runs`` (output scale by ``log_output``, else by the settings)."""
        if log_output is None:
            log_output = _log_output(self.settings, runs)
        return FunctionalEmulator(
            runs, self.physics, log_output=log_output, kernel=self.settings.kernel,  # type: ignore[arg-type]
            box=self.box, seed=self.settings.seed,
        )  # fmt: skip


def _log_output(settings: EmulatorSettings, runs: FunctionalRuns) -> bool:
    """``log_output``; ``"auto"``: every curve positive, spanning two decades or more."""
    if settings.log_output != "auto":
        return bool(settings.log_output)
    curves = np.asarray(runs.curves, dtype=float)
    if curves.size == 0 or not np.all(curves > 0):
        return False
    return bool(log_scaled(np.array([curves.min()]), np.array([curves.max()]))[0])


def study_functional_physics(
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
) -> FunctionalEmulatedPhysics:
    """Build (or refit from cached curves) a study's functional emulator; return its physics.

    Parameters are those of :func:`kohpymc.emulator.study.study_physics`;
    ``settings.functional`` names the grid's inputs.

    Returns
    -------
    FunctionalEmulatedPhysics

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import decay
    >>> data = decay.generate_data(decay.CALIBRATION_TIMES, seed=1)
    >>> physics = study_functional_physics(EmulatorSettings(runs=12, functional=("t",)),
    ...                                    decay.physics_model(), data, tempfile.mkdtemp())
    >>> physics.emulator.n_runs, physics.emulator.log_output
    (12, True)
    """
    folder = Path(out_dir) / "emulator"
    folder.mkdir(parents=True, exist_ok=True)
    data = (calibration,) if validation is None else (calibration, validation)
    study = CurveStudy.of(
        settings, physics, *data, cache=folder / "runs", workers=workers, scheduler=scheduler
    )
    key = ""
    if settings.sequential > 0:
        key = digest(
            [
                rounds_key(settings, physics, calibration, formulations, sampling),
                None if validation is None else data_fingerprint(validation),
            ]
        )
    emulator = _restored(study, folder, key)
    restored = emulator is not None
    if emulator is None:
        emulator = study.fit(study.run(study.design(settings.runs, settings.design, settings.seed)))
        if settings.sequential > 0:
            emulator = run_rounds(
                settings, physics, calibration, emulator, folder, formulations=formulations,
                sampling=sampling, workers=workers, scheduler=scheduler,
            )  # fmt: skip
            _write_record(folder, key, emulator)
    if not (restored and warn_recorded(folder, EmulatorsAtData.of(emulator, calibration))):
        _write_checks(study, emulator, calibration, folder)
    write_settings(folder, settings)
    write_functional_emulator(folder, emulator)
    return emulator.physics_model(covariance=settings.covariance)  # type: ignore[arg-type]


def _write_record(folder: Path, key: str, emulator: FunctionalEmulator) -> None:
    """``rounds.json``: the key, the final design and output scale (a rerun refits them)."""
    design = emulator.runs.design
    record = {
        "key": key,
        "columns": list(design.columns),
        "design": design.to_numpy(dtype=float).tolist(),
        "log_output": emulator.log_output,
    }
    _write_json(folder / ROUNDS_RECORD, record)


def _restored(study: CurveStudy, folder: Path, key: str) -> FunctionalEmulator | None:
    """The final emulator of earlier rounds under ``key``, refitted from the cached curves.

    None without rounds (empty ``key``), without a record or with another key.
    """
    record = read_rounds_record(folder, key)
    if record is None:
        return None
    design = pd.DataFrame(record["design"], columns=record["columns"])
    return study.fit(study.run(design), log_output=bool(record["log_output"]))


def _write_checks(
    study: CurveStudy, emulator: FunctionalEmulator, calibration: CalibrationData, folder: Path
) -> None:
    """``check.json``/``.png`` on held-out curves, ``check_at_data.json``; warn from the latter.

    The held-out curves (a fifth of the first θ, at least 3, at every setting) score the
    emulator over the prior box, most of which the posterior never visits; they are
    written, not warned, and their problems are named in the warning of a failed check
    at the data (:func:`~kohpymc.emulator.study.write_check_at_data`).
    """
    settings = study.settings
    n_theta = max(3, math.ceil(settings.runs / len(study.points) / 5))
    design = study.design(n_theta * len(study.points), "sobol", settings.seed + 1)
    held_out = emulator.held_out_check(study.run(design))
    write_check(folder, held_out)
    write_check_at_data(
        folder, EmulatorsAtData.of(emulator, calibration), held_out.problems, advice=ADVICE,
        workers=study.workers, scheduler=study.scheduler,
    )  # fmt: skip


def write_functional_emulator(folder: Path, emulator: FunctionalEmulator) -> None:
    """``emulator.json`` (basis, weight GPs), ``runs.csv`` (every curve's row), ``grid.csv``.

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import decay
    >>> data = decay.generate_data(decay.CALIBRATION_TIMES, seed=1)
    >>> study = CurveStudy.of(EmulatorSettings(functional=("t",)), decay.physics_model(),
    ...                       data)
    >>> folder = Path(tempfile.mkdtemp())
    >>> write_functional_emulator(folder, study.fit(study.run(study.design(8, "lhs", 0))))
    >>> sorted(p.name for p in folder.iterdir())
    ['emulator.json', 'grid.csv', 'runs.csv']
    """
    record = {
        "emulator": repr(emulator),
        "kernel": emulator.kernel,
        "functional": list(emulator.functional),
        "columns": list(emulator.columns),
        "log_output": emulator.log_output,
        "components": emulator.n_components,
        "explained_variance": emulator.explained,
        "weight_gps": [
            {
                "lengthscales_unit_box": [float(v) for v in h.lengthscales],
                "amplitude": h.amplitude,
                "nugget": h.nugget,
                "log_posterior": h.log_posterior,
            }
            for h in emulator.hypers
        ],
        "runs": emulator.n_runs,
        "failed_runs": int(len(emulator.runs.failed)),
    }
    _write_json(folder / "emulator.json", record)
    runs = emulator.runs
    table = pd.concat([runs.design.assign(error=""), runs.failed], ignore_index=True)
    write_atomic(folder / "runs.csv", lambda tmp: table.to_csv(tmp, index=False))
    write_atomic(folder / "grid.csv", lambda tmp: runs.grid.to_csv(tmp, index=False))
