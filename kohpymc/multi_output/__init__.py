"""Several outputs calibrate one θ jointly (``output = ["u", "strain"]``).

* :class:`MultiOutputData`: one data set per output (long form), each with its own σ_obs;
* :class:`MultiOutputPhysics`: ``function(inputs, params) -> {output: array}`` with
  shared parameters; each output is an ordinary :class:`~kohpymc.PhysicsModel`;
* :func:`compose_multi_output_model`: the joint PyMC model, each output a named
  sub-model (``u::y``, ``u::sigma_obs``, ``strain::delta`` ...) with its own discrepancy
  (independent by default) or one :class:`Coregionalized` GP over all outputs;
* :func:`calibrate_outputs`, :func:`predict_output`, :func:`stacked_taylor_check`;
* :func:`output_reliability` / :func:`reliability_table`: r(x) per output and combined;
* :func:`output_loo`: LOO comparison per output and combined (pointwise values:
  :func:`~kohpymc.multi_output.loo.add_pointwise_log_likelihood`);
* :func:`discover_outputs`: :func:`kohpymc.discover` on each output;
* :func:`emulate_outputs` / :func:`emulated_outputs`: an expensive simulator through one
  GP emulator per output (one design, every run giving all outputs);
* :func:`load_multi_output_study` / :func:`run_multi_output_study`: the same from TOML.
"""

from kohpymc.multi_output.calibration import (
    MultiOutputCalibration,
    calibrate_outputs,
    predict_output,
    stacked_taylor_check,
)
from kohpymc.multi_output.config import MultiOutputStudySpec, load_multi_output_study
from kohpymc.multi_output.coregionalized import Coregionalized
from kohpymc.multi_output.data import MultiOutputData
from kohpymc.multi_output.discovery import discover_outputs
from kohpymc.multi_output.emulator import emulate_outputs, emulated_outputs
from kohpymc.multi_output.loo import output_loo
from kohpymc.multi_output.model import MultiOutputModel, compose_multi_output_model
from kohpymc.multi_output.physics import MultiOutputPhysics
from kohpymc.multi_output.reliability import (
    OutputReliability,
    output_reliability,
    reliability_table,
)
from kohpymc.multi_output.study import MultiOutputStudyResult, run_multi_output_study

__all__ = [
    "MultiOutputData",
    "MultiOutputPhysics",
    "MultiOutputModel",
    "compose_multi_output_model",
    "Coregionalized",
    "MultiOutputCalibration",
    "calibrate_outputs",
    "predict_output",
    "stacked_taylor_check",
    "OutputReliability",
    "output_reliability",
    "reliability_table",
    "load_multi_output_study",
    "MultiOutputStudySpec",
    "run_multi_output_study",
    "MultiOutputStudyResult",
    "discover_outputs",
    "output_loo",
    "emulate_outputs",
    "emulated_outputs",
]
