"""kohpymc: Bayesian calibration of physics models with model discrepancy on PyMC.

Kennedy–O'Hagan form ``y_D = G(x; θ) + δ(x) + ε`` with the discrepancy priors of
Ling, Mullins & Mahadevan, "Selection of model discrepancy priors in Bayesian
calibration".  This namespace is the user API; the modules hold the rest.
"""

from importlib.metadata import PackageNotFoundError, version

# before anything imports arviz: its once-a-day "undergoing a major refactor" FutureWarning
# (and setuptools' deprecation notices) say nothing about the user's problem
from kohpymc import warning_filters as _warning_filters  # noqa: F401 - filters on import

# isort: split
from kohpymc import discrepancy as _discrepancy
from kohpymc.calibration import Calibration, calibrate, predict
from kohpymc.combination import combine_posteriors, loo_weights, reliability_weights
from kohpymc.config import StudyConfigError, StudySpec, load_study
from kohpymc.data import CalibrationData, pooled_replicate_sd
from kohpymc.diagnostics import SamplerTroubleWarning, SlowSamplingWarning, sampler_diagnostics
from kohpymc.discovery import DiscoveryReport, discover
from kohpymc.discrepancy import *  # noqa: F403 - every registered formulation class
from kohpymc.emulator import (
    EmulatedPhysics,
    Emulator,
    EmulatorCheck,
    EmulatorWarning,
    FunctionalEmulatedPhysics,
    FunctionalEmulator,
    FunctionalRuns,
    check_emulator,
    design_box,
    emulate,
    extend_design,
    run_curves,
    run_design,
    sequential_design,
    space_filling_design,
)
from kohpymc.execution import TaskOutcome, run_tasks
from kohpymc.identifiability import (
    IdentifiabilityReport,
    IdentifiabilityWarning,
    check_formulation,
    fisher_information_check,
    taylor_check,
)
from kohpymc.initialization import MultistartResult, multistart_least_squares, prior_box
from kohpymc.model import build_model
from kohpymc.multi_output import (
    Coregionalized,
    MultiOutputCalibration,
    MultiOutputData,
    MultiOutputPhysics,
    calibrate_outputs,
    discover_outputs,
    load_multi_output_study,
    output_reliability,
    reliability_table,
    run_multi_output_study,
)
from kohpymc.physics import PhysicsModel, PhysicsModelError
from kohpymc.prior_bounds import PriorBoundWarning
from kohpymc.priors import Custom, HalfNormal, LogNormal, LogUniform, Normal, Prior, Uniform
from kohpymc.progress import TaskDisplay, report_note, report_phase, task_display
from kohpymc.sbc import CalibrationCheck, check_calibration
from kohpymc.study import StudyResult, run_study
from kohpymc.validation import Reliability, reliability

try:
    __version__ = version("kohpymc")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = [
    # physics, data, priors
    "PhysicsModel",
    "PhysicsModelError",
    "CalibrationData",
    "pooled_replicate_sd",
    "Prior",
    "Uniform",
    "LogUniform",
    "Normal",
    "LogNormal",
    "HalfNormal",
    "Custom",
    # discrepancy formulations (M0–M6, GridGP, ...) and how to write one
    *_discrepancy.__all__,
    # calibration
    "build_model",
    "calibrate",
    "Calibration",
    "predict",
    "multistart_least_squares",
    "MultistartResult",
    "prior_box",
    "sampler_diagnostics",
    "SamplerTroubleWarning",
    "SlowSamplingWarning",
    "PriorBoundWarning",
    # several outputs calibrating one θ jointly
    "MultiOutputData",
    "MultiOutputPhysics",
    "calibrate_outputs",
    "MultiOutputCalibration",
    "Coregionalized",
    "output_reliability",
    "reliability_table",
    "discover_outputs",
    "load_multi_output_study",
    "run_multi_output_study",
    # emulating an expensive simulator
    "Emulator",
    "EmulatedPhysics",
    "FunctionalEmulator",
    "FunctionalEmulatedPhysics",
    "FunctionalRuns",
    "run_curves",
    "emulate",
    "sequential_design",
    "check_emulator",
    "EmulatorCheck",
    "EmulatorWarning",
    "design_box",
    "space_filling_design",
    "extend_design",
    "run_design",
    # identifiability
    "taylor_check",
    "check_formulation",
    "fisher_information_check",
    "IdentifiabilityReport",
    "IdentifiabilityWarning",
    # validation, weights, studies, discovery
    "reliability",
    "Reliability",
    "reliability_weights",
    "combine_posteriors",
    "loo_weights",
    "run_study",
    "StudyResult",
    "load_study",
    "StudySpec",
    "StudyConfigError",
    "discover",
    "DiscoveryReport",
    # where tasks run (in this process or on Dask) and their progress
    "run_tasks",
    "TaskOutcome",
    "task_display",
    "TaskDisplay",
    "report_phase",
    "report_note",
    # does a set-up recover the truth? (simulation-based calibration)
    "check_calibration",
    "CalibrationCheck",
    "__version__",
]
