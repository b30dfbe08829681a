"""Emulating an expensive simulator: design, runs, a GP emulator, its checks.

* :mod:`~kohpymc.emulator.design`: space-filling designs over the calibration inputs ×
  the prior box of θ (maximin Latin hypercube, Sobol) and their extension;
* :mod:`~kohpymc.emulator.runs`: simulator runs at a design as tasks
  (:func:`kohpymc.run_tasks`), cached on disk, failures recorded and skipped;
* :mod:`~kohpymc.emulator.gp`: :class:`Emulator`, a GP over (inputs, θ) whose mean and
  variance enter the calibration as an :class:`EmulatedPhysics` model;
* :mod:`~kohpymc.emulator.functional`: :class:`FunctionalEmulator`, curves on a fixed
  grid through a principal-component basis with a GP per weight (GPMSA / SEPIA);
* :mod:`~kohpymc.emulator.checking`: leave-one-out or held-out scores, a figure and an
  :class:`EmulatorWarning` when the emulator is not fit for calibration;
* :mod:`~kohpymc.emulator.sequential`: :func:`emulate` (design, run, fit) and
  :func:`sequential_design` (add runs at posterior draws until the posterior settles);
* :mod:`~kohpymc.emulator.at_data`: :class:`EmulatorsAtData`, a simulator's emulators
  (one per output) with their calibration data, as the check at the data sees them;
* :mod:`~kohpymc.emulator.refinement`: :func:`refine_at_data` (add runs around the
  emulator's best fit until :func:`check_at_data` passes; no sampling), and
  :func:`refine_emulators_at_data` for several outputs;
* :mod:`~kohpymc.emulator.posterior_check`: :func:`check_at_posterior`, the emulator
  scored against one simulator run at a formulation's posterior mean;
* :mod:`~kohpymc.emulator.posterior_rounds`: :func:`refine_at_posteriors` (runs at the
  posteriors where that check failed, the emulator refitted).
"""

from kohpymc.emulator.at_data import EmulatorsAtData
from kohpymc.emulator.checking import (
    EmulatorCheck,
    EmulatorWarning,
    OutputsCheck,
    check_at_data,
    check_emulator,
    check_emulators_at_data,
)
from kohpymc.emulator.design import (
    design_box,
    extend_design,
    maximin_distance,
    space_filling_design,
)
from kohpymc.emulator.functional import (
    FunctionalEmulatedPhysics,
    FunctionalEmulator,
    FunctionalRuns,
    merged_curves,
    posterior_curve_design,
    run_curves,
)
from kohpymc.emulator.gp import EmulatedPhysics, Emulator, GPHyperparameters
from kohpymc.emulator.posterior_check import check_at_posterior
from kohpymc.emulator.posterior_rounds import refine_at_posteriors
from kohpymc.emulator.refinement import (
    Refinement,
    local_design,
    refine_at_data,
    refine_emulators_at_data,
)
from kohpymc.emulator.runs import SimulatorRuns, run_design
from kohpymc.emulator.sequential import (
    SequentialDesign,
    emulate,
    fit_emulator,
    posterior_design,
    sequential_design,
)

__all__ = [
    "EmulatorCheck",
    "EmulatorWarning",
    "check_at_data",
    "check_at_posterior",
    "check_emulator",
    "check_emulators_at_data",
    "EmulatorsAtData",
    "OutputsCheck",
    "Emulator",
    "EmulatedPhysics",
    "GPHyperparameters",
    "FunctionalEmulator",
    "FunctionalEmulatedPhysics",
    "FunctionalRuns",
    "run_curves",
    "design_box",
    "extend_design",
    "maximin_distance",
    "space_filling_design",
    "SimulatorRuns",
    "run_design",
    "SequentialDesign",
    "emulate",
    "fit_emulator",
    "merged_curves",
    "posterior_curve_design",
    "posterior_design",
    "sequential_design",
    "Refinement",
    "local_design",
    "refine_at_data",
    "refine_at_posteriors",
    "refine_emulators_at_data",
]
