"""kohpymc: Bayesian calibration of physics models with model discrepancy on PyMC.

Kennedy–O'Hagan form ``y_D = G(x; θ) + δ(x) + ε`` with the discrepancy priors of
Ling, Mullins & Mahadevan, "Selection of model discrepancy priors in Bayesian
calibration".
"""

from importlib.metadata import PackageNotFoundError, version

from kohpymc.calibration import calibrate, predict
from kohpymc.combination import combine_posteriors, loo_weights, reliability_weights
from kohpymc.config import StudySpec, load_study
from kohpymc.data import CalibrationData, pooled_replicate_sd
from kohpymc.diagnostics import SamplerTroubleWarning, convergence_problems, sampler_diagnostics
from kohpymc.discrepancy import (
    ConstantBias,
    DecayingVariance,
    Discrepancy,
    GaussianProcess,
    GridGP,
    IIDGaussian,
    InputDependentGaussian,
    LinearBasis,
    NoDiscrepancy,
    NonStationaryGP,
    ParametricFunction,
)
from kohpymc.identifiability import (
    IdentifiabilityReport,
    IdentifiabilityWarning,
    check_formulation,
    fisher_information_check,
    taylor_check,
)
from kohpymc.model import build_model
from kohpymc.physics import PhysicsModel, PhysicsModelError
from kohpymc.priors import Custom, HalfNormal, LogNormal, Normal, Prior, Uniform
from kohpymc.reliability import Reliability, reliability
from kohpymc.study import StudyResult, default_formulations, run_study

try:
    __version__ = version("kohpymc")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = [
    "PhysicsModel",
    "PhysicsModelError",
    "CalibrationData",
    "pooled_replicate_sd",
    "Prior",
    "Uniform",
    "Normal",
    "LogNormal",
    "HalfNormal",
    "Custom",
    "Discrepancy",
    "NoDiscrepancy",
    "ConstantBias",
    "IIDGaussian",
    "InputDependentGaussian",
    "GaussianProcess",
    "GridGP",
    "NonStationaryGP",
    "DecayingVariance",
    "LinearBasis",
    "ParametricFunction",
    "build_model",
    "calibrate",
    "predict",
    "sampler_diagnostics",
    "taylor_check",
    "check_formulation",
    "fisher_information_check",
    "IdentifiabilityReport",
    "IdentifiabilityWarning",
    "convergence_problems",
    "SamplerTroubleWarning",
    "reliability",
    "Reliability",
    "reliability_weights",
    "combine_posteriors",
    "loo_weights",
    "run_study",
    "StudyResult",
    "default_formulations",
    "load_study",
    "StudySpec",
    "__version__",
]
