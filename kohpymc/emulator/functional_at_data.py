"""A functional (principal-component) emulator at its calibration data.

The check at the data (:func:`~kohpymc.emulator.checking.check_at_data`) sees an emulator
through :class:`~kohpymc.emulator.at_data.EmulatorsAtData`: where its runs' θ are, what the
simulator gives at a θ on the calibration rows, and what the emulator predicts there.
:class:`CurvesAtData` answers these for a
:class:`~kohpymc.emulator.functional.FunctionalEmulator`: the simulator runs one whole curve
per scalar setting of the data (:func:`~kohpymc.emulator.functional.run_curves`, cached
like the design's curves), read at the data's rows as the emulator reads its grid
(:meth:`~kohpymc.emulator.functional.FunctionalEmulator.at_rows`).  The rest of the check
(best fit, scores, the linearised move of θ and widening of its posterior) is the scalar
emulator's, unchanged.

The held-out curves of a functional study lie all over the prior box; the posterior
occupies a small part of it.  On an oral-dose pharmacokinetics study the held-out bands
covered 0.72–0.74 of the held-out values (< 0.83: a warning) while, at the posterior, the
emulator's error was rms 0.02 against a misfit of 0.15 to the data: the check at the data
is what tells whether the emulator is fit for *this* calibration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.emulator.at_data import SINGLE, EmulatorsAtData, linearisation, runs_at
from kohpymc.emulator.functional import FunctionalEmulator, at_settings, distinct_rows, run_curves

__all__ = ["CurvesAtData"]


@dataclass(frozen=True)
class CurvesAtData(EmulatorsAtData):
    """A functional emulator, its simulator and its calibration data (one output).

    Examples
    --------
    >>> from kohpymc.examples import decay
    >>> from kohpymc.emulator import space_filling_design
    >>> physics, data = decay.physics_model(), decay.generate_data(seed=1)
    >>> grid = {"t": sorted(set(data.inputs["t"]))}
    >>> design = space_filling_design({"A": (1.0, 3.0), "k": (0.3, 1.0)}, 10, seed=1)
    >>> target = EmulatorsAtData.of(FunctionalEmulator(run_curves(physics, design, grid),
    ...                                                physics), data)
    >>> type(target).__name__, target.run_thetas().shape
    ('CurvesAtData', (10, 2))
    >>> simulated = target.simulated_at({"A": 2.0, "k": 0.5})["output"]
    >>> bool(np.allclose(simulated, 2.0 * np.exp(-0.5 * data.inputs["t"])))
    True
    """

    @classmethod
    def of(cls, emulator: Any, data: CalibrationData) -> CurvesAtData:
        """The emulator's own simulator and the data."""
        if not isinstance(emulator, FunctionalEmulator):
            raise TypeError(f"CurvesAtData: needs a FunctionalEmulator, got {emulator!r}")
        # a FunctionalEmulator answers the calls the check makes of an Emulator
        return cls(emulator.physics, {SINGLE: emulator}, {SINGLE: data})  # type: ignore[dict-item]

    @property
    def curves(self) -> FunctionalEmulator:
        """The functional emulator."""
        return self.emulators[SINGLE]  # type: ignore[return-value]

    def _design_failures(self) -> tuple[int, int]:
        """Failed and all curves of the emulator's design."""
        runs = self.curves.runs
        return len(runs.failed), runs.n_runs + len(runs.failed)

    def run_thetas(self) -> np.ndarray:
        """The distinct θ of the curves (rows; columns :attr:`parameters`)."""
        return self.curves.runs.design[self.parameters].drop_duplicates().to_numpy(float)

    def simulated_at(
        self,
        theta: dict[str, float],
        *,
        cache: str | Path | None = None,
        workers: int = 1,
        scheduler: Any = None,
    ) -> dict[str, np.ndarray]:
        """The simulator at ``theta`` on the calibration rows: one curve per setting."""
        emulator, data = self.curves, self.data[SINGLE]
        scalar = emulator.scalar_inputs
        design = at_settings(
            pd.DataFrame([theta]), distinct_rows(scalar, data), scalar, self.parameters
        )
        runs = run_curves(
            self.simulator, design, emulator.runs.grid, cache=cache, workers=workers,
            scheduler=scheduler,
        )  # fmt: skip
        if len(runs.failed):
            total = len(runs.failed) + runs.n_runs
            raise self._failed_at(theta, runs.failed, total, "curves")
        return {SINGLE: emulator.at_rows(runs, data.inputs)}

    def linearised(
        self, name: str, theta: Mapping[str, float]
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """:func:`~kohpymc.emulator.at_data.linearisation`, ``Σ_η`` computed in numpy.

        (The same matrix as the emulator's ``covariance_tensor``, without compiling it:
        the first compilation took 15 s.)
        """
        data = self.data[name]
        _, covariance = self.curves.predict_covariance(data.inputs, dict(theta))
        return linearisation(self.curves, data, theta, covariance)  # type: ignore[arg-type]

    def predicted_at(self, name: str, theta: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """The emulator's mean and variance at ``theta`` on the calibration rows.

        Curves run at ``theta`` itself (:func:`~kohpymc.emulator.at_data.runs_at`) are
        left out of the weight GPs, else the prediction would only repeat them.
        """
        emulator = self.curves
        return emulator.predict(self.data[name].inputs, theta, runs_at(emulator, theta))
