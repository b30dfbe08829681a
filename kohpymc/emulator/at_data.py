"""The emulators of one calibration at its data: one per output, sharing θ and the simulator.

The check at the data (:func:`~kohpymc.emulator.checking.check_at_data`) and the
refinement rounds (:mod:`~kohpymc.emulator.refinement`) see a calibration through
:class:`EmulatorsAtData`: the simulator that runs, one emulator per output and that
output's calibration data.  A single-output study is the case of one output
(:meth:`EmulatorsAtData.of`); a multi-output one has every output's emulator fitted to
the same runs, each run giving all outputs from one simulator call
(:meth:`EmulatorsAtData.of_outputs`).  The outputs are stacked in the units of their
noise: :meth:`EmulatorsAtData.whitened_linearisation` divides each output's rows by its
noise sd, so the joint least squares weighs each output by ``1/σ_k²``.  A functional
emulator (:class:`~kohpymc.emulator.functional.FunctionalEmulator`) is seen through the
subclass :class:`~kohpymc.emulator.functional_at_data.CurvesAtData`, which
:meth:`EmulatorsAtData.of` returns for it: its simulator runs whole curves.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from scipy import linalg

from kohpymc.data import CalibrationData
from kohpymc.emulator.gp import Emulator
from kohpymc.emulator.runs import SimulatorRuns, run_design
from kohpymc.emulator.sequential import refit

if TYPE_CHECKING:
    from kohpymc.multi_output.physics import MultiOutputPhysics

__all__ = ["EmulatorsAtData", "linearisation", "runs_at"]

#: the output name of a single-output calibration in :class:`EmulatorsAtData`
SINGLE = "output"


def linearisation(
    emulator: Emulator,
    data: CalibrationData,
    theta: Mapping[str, float],
    covariance: np.ndarray | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """The emulator linearised at ``theta`` on the data's rows: ``(J, σ, Σ_η)``.

    ``J`` is the Jacobian of the emulator's mean with respect to θ (the emulated
    physics' finite differences; rows = data rows, columns = parameters in their own
    units), ``σ`` the data's noise sd (known or pooled from replicates) or else the rms
    residual of the emulator's mean at ``theta``, and ``Σ_η`` the emulator's covariance
    between the rows.  ``(Jᵀ (σ² I + Σ_η)⁻¹ J)⁻¹`` is then the linearised posterior
    covariance of θ through the emulator (flat prior).  ``covariance``: ``Σ_η`` when
    already known (else evaluated from the emulator's ``covariance_tensor``).

    Examples
    --------
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> data = beam.generate_data(seed=1)
    >>> J, noise, cov = linearisation(emulate(beam.physics_model(), data, runs=30), data,
    ...                               {"E": 200.0})
    >>> J.shape == (data.n, 1), cov.shape == (data.n, data.n)
    (True, True)
    """
    names = list(emulator.physics.parameters)
    inputs = {k: np.asarray(data.inputs[k], float) for k in emulator.physics.inputs}
    point = np.array([theta[k] for k in names], dtype=float)
    X = np.column_stack([inputs[k] for k in emulator.physics.inputs])
    if covariance is None:
        covariance = np.asarray(emulator.covariance_tensor(point, X).eval(), dtype=float)
    cov = covariance
    noise = data.noise_sd
    if noise is None:
        mean, _ = emulator.predict(inputs, point)
        noise = float(np.sqrt(np.mean((np.asarray(data.y, float) - mean) ** 2)))
    J = emulator.physics_model().jacobian_matrix(inputs, dict(theta))  # finite differences
    return J, float(noise), cov


class SimulatorFailedAt(RuntimeError):
    """The simulator failed at a θ where a check needed its outputs.

    ``where`` says on how many of the rows (or curves), ``first`` is the first error; the
    message is that of the check at the data.
    """

    def __init__(self, message: str, where: str, first: str) -> None:
        super().__init__(message)
        self.where = where
        self.first = first


@dataclass(frozen=True)
class EmulatorsAtData:
    """A simulator, one emulator per output and each output's calibration data.

    Attributes
    ----------
    simulator : PhysicsModel or MultiOutputPhysics
        What runs (one call per θ gives every output).
    emulators : dict of str to Emulator
        Output -> its emulator; all fitted to the same runs, on the same box.
    data : dict of str to CalibrationData
        Output -> its calibration data (the outputs checked at the data).
    predict_rows : numpy.ndarray, optional
        More input rows (columns: the simulator's inputs) where every θ of a check or
        refinement round runs besides the calibration rows: the validation rows
        (:meth:`also_at`), so that the study's predictions there rest on runs at the
        refined θ, not on the first design's few (one simulator call per θ either way).

    Examples
    --------
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> data = beam.generate_data(seed=1)
    >>> target = EmulatorsAtData.of(emulate(beam.physics_model(), data, runs=10), data)
    >>> target.outputs, target.n_runs, target.rows().shape == (data.n, 2)
    (('output',), 10, True)
    """

    simulator: Any
    emulators: dict[str, Emulator]
    data: dict[str, CalibrationData]
    predict_rows: np.ndarray | None = None

    @classmethod
    def of(cls, emulator: Any, data: CalibrationData) -> EmulatorsAtData:
        """One output: the emulator's own simulator and the data.

        A :class:`~kohpymc.emulator.functional.FunctionalEmulator` gives a
        :class:`~kohpymc.emulator.functional_at_data.CurvesAtData` (its simulator runs
        whole curves).
        """
        from kohpymc.emulator.functional import FunctionalEmulator

        if isinstance(emulator, FunctionalEmulator) and cls is EmulatorsAtData:
            from kohpymc.emulator.functional_at_data import CurvesAtData

            return CurvesAtData.of(emulator, data)
        return cls(emulator.physics, {SINGLE: emulator}, {SINGLE: data})

    @classmethod
    def of_outputs(
        cls,
        simulator: MultiOutputPhysics,
        emulators: Mapping[str, Emulator],
        data: Any,
    ) -> EmulatorsAtData:
        """Several outputs of one simulator and their data (a ``MultiOutputData``).

        Outputs without calibration data are refitted with the others but not checked.
        """
        with_data = {k: data[k] for k in emulators if k in data.outputs}
        if not with_data:
            raise ValueError(
                f"EmulatorsAtData: none of the emulated outputs {list(emulators)} has "
                f"calibration data (outputs {list(data.outputs)})"
            )
        return cls(simulator, dict(emulators), with_data)

    @property
    def outputs(self) -> tuple[str, ...]:
        """The outputs' names."""
        return tuple(self.emulators)

    @property
    def single(self) -> bool:
        """Whether the simulator has one output (its runs have no per-output columns)."""
        return not getattr(self.simulator, "outputs", ())

    @property
    def first(self) -> Emulator:
        """The first output's emulator (every one has the same columns and box)."""
        return next(iter(self.emulators.values()))

    @property
    def parameters(self) -> list[str]:
        """The calibration parameters."""
        return list(self.first.runs.parameters)

    @property
    def inputs(self) -> list[str]:
        """The simulator's inputs."""
        return list(self.first.runs.inputs)

    @property
    def n_runs(self) -> int:
        """Runs the emulators are fitted to."""
        return self.first.n_runs

    def rows(self) -> np.ndarray:
        """The distinct calibration input rows over every output (columns: inputs)."""
        names = tuple(self.inputs)
        return np.unique(np.vstack([d.matrix(names) for d in self.data.values()]), axis=0)

    def also_at(self, data: Any) -> EmulatorsAtData:
        """The same, each θ of a round also run at the input rows of ``data``.

        ``data``: a ``CalibrationData`` or ``MultiOutputData`` (e.g. the validation data;
        None: unchanged).  The check at the data still scores the calibration rows only.

        Examples
        --------
        >>> from kohpymc.emulator import emulate
        >>> from kohpymc.examples import beam
        >>> data, new = beam.generate_data(seed=1), beam.generate_data((3.5,), seed=2)
        >>> target = EmulatorsAtData.of(emulate(beam.physics_model(), data, runs=10), data)
        >>> len(target.design_rows()), len(target.also_at(new).design_rows())
        (20, 40)
        """
        if data is None:
            return self
        names = tuple(self.inputs)
        sets = [data[k] for k in data.outputs] if hasattr(data, "outputs") else [data]
        rows = np.vstack([d.matrix(names) for d in sets])
        return replace(self, predict_rows=np.unique(rows, axis=0))

    def design_rows(self) -> np.ndarray:
        """The distinct input rows a round runs each θ at: calibration and ``predict_rows``."""
        if self.predict_rows is None:
            return self.rows()
        return np.unique(np.vstack([self.rows(), self.predict_rows]), axis=0)

    def design(self, thetas: pd.DataFrame) -> pd.DataFrame:
        """Each θ (a row of ``thetas``) at every row of :meth:`design_rows`."""
        X = self.design_rows()
        values = thetas[self.parameters].to_numpy(float)
        blocks = [np.column_stack([X, np.tile(theta, (len(X), 1))]) for theta in values]
        return pd.DataFrame(np.vstack(blocks), columns=[*self.inputs, *self.parameters])

    def run(
        self,
        design: pd.DataFrame,
        *,
        cache: str | Path | None = None,
        workers: int = 1,
        scheduler: Any = None,
    ) -> SimulatorRuns:
        """The simulator at the design's points (one call per θ, cached)."""
        return run_design(self.simulator, design, cache=cache, workers=workers, scheduler=scheduler)

    def run_thetas(self) -> np.ndarray:
        """The distinct θ of the runs (rows; columns :attr:`parameters`)."""
        return self.first.runs.points[self.parameters].drop_duplicates().to_numpy(float)

    def simulated_at(
        self,
        theta: dict[str, float],
        *,
        cache: str | Path | None = None,
        workers: int = 1,
        scheduler: Any = None,
    ) -> dict[str, np.ndarray]:
        """Output -> the simulator at ``theta`` on that output's calibration rows (one call)."""
        design = self.design(pd.DataFrame([theta]))
        runs = self.run(design, cache=cache, workers=workers, scheduler=scheduler)
        if len(runs.failed):
            failed = runs.failed
            raise self._failed_at(theta, failed, len(failed) + len(runs.points))
        columns = [*self.inputs, *self.parameters]
        simulated = {}
        for k, data in self.data.items():
            rows = pd.DataFrame({i: np.asarray(data.inputs[i], float) for i in self.inputs})
            rows = rows.assign(**theta)
            done = self.output_runs(runs, k).points[[*columns, "output"]]
            done = done.drop_duplicates(subset=columns)
            simulated[k] = rows.merge(done, on=columns, how="left")["output"].to_numpy(float)
        return simulated

    def _design_failures(self) -> tuple[int, int]:
        """Failed and all runs of the emulator's design."""
        design = self.first.runs
        return len(design.failed), len(design.points) + len(design.failed)

    def _failed_at(
        self, theta: Mapping[str, float], failed: pd.DataFrame, total: int,
        what: str = "calibration rows",
    ) -> SimulatorFailedAt:  # fmt: skip
        """Why the check at the data cannot go on: the simulator fails at the best fit."""
        point = ", ".join(f"{k}={v:.6g}" for k, v in theta.items())
        design_failed, design_total = self._design_failures()
        first = str(failed["error"].iloc[0])
        return SimulatorFailedAt(
            f"check at the data: the simulator failed at the emulator's best fit to the data "
            f"{{{point}}} on {len(failed)} of {total} {what} (first: "
            f"{failed['error'].iloc[0]}); {design_failed} of the emulator's {design_total} "
            "design runs failed too. The emulator has no run where the data lie, so a "
            "calibration through it would rest on none: make the simulator run there, or "
            "narrow the parameters' prior box to where it runs",
            f"{len(failed)} of {total} {what}",
            first,
        )

    def predicted_at(self, name: str, theta: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """Output ``name``'s emulator at ``theta`` on its calibration rows: mean, variance.

        Runs made at ``theta`` itself (:func:`runs_at`) are left out, else the
        prediction would only repeat them.
        """
        emulator, data = self.emulators[name], self.data[name]
        Z = emulator._matrix(data.inputs, theta)
        return emulator.predict_matrix(Z, without=runs_at(emulator, theta))

    @staticmethod
    def output_runs(runs: SimulatorRuns, name: str) -> SimulatorRuns:
        """One output's runs (the runs themselves for a single-output simulator)."""
        return runs.output(name) if runs.outputs else runs

    def refit(self, runs: SimulatorRuns, *, seed: int = 0) -> EmulatorsAtData:
        """Every emulator refitted to its runs and its output of ``runs``."""
        emulators = {
            k: refit(em, self.output_runs(runs, k), seed=seed) for k, em in self.emulators.items()
        }
        return replace(self, emulators=emulators)

    def linearised(
        self, name: str, theta: Mapping[str, float]
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """Output ``name``'s :func:`linearisation` at ``theta``: ``(J, σ, Σ_η)``."""
        return linearisation(self.emulators[name], self.data[name], theta)

    def whitened_linearisation(self, theta: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """``(J̃, Σ̃)``: every output's :func:`linearisation` stacked, in its noise's units.

        Output ``k``'s rows of ``J`` are divided by its ``σ_k`` and its block of the
        emulator's covariance by ``σ_k²`` (block-diagonal: the outputs' emulators are
        independent), so ``(J̃ᵀ (I + Σ̃)⁻¹ J̃)⁻¹`` is the linearised joint posterior
        covariance of θ through the emulators (flat prior).
        """
        blocks, covs = [], []
        for k in self.data:
            J, noise, cov = self.linearised(k, theta)
            blocks.append(J / noise)
            covs.append(cov / noise**2)
        return np.vstack(blocks), linalg.block_diag(*covs)


def runs_at(emulator: Any, theta: Mapping[str, float]) -> np.ndarray:
    """Mask of the runs made at ``theta``: every parameter within 1e-4 of the box's width.

    (The best fit may stop a few ulps from a run's θ; a run that near tells the emulator
    what one at θ̂ would.)  ``emulator``: an ``Emulator`` or ``FunctionalEmulator``.
    """
    names = list(emulator.runs.parameters)
    cols = [emulator.columns.index(k) for k in names]
    unit = emulator.parameters_to_unit(np.array([[theta[k] for k in names]], dtype=float))
    return np.all(np.abs(emulator.U[:, cols] - unit) < 1e-4, axis=1)
