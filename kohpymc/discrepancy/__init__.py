"""Discrepancy formulations M0–M5 (paper Section 3), one module each."""

from kohpymc.discrepancy.base import Discrepancy, ModelContext
from kohpymc.discrepancy.constant import ConstantBias
from kohpymc.discrepancy.functions import LinearBasis, ParametricFunction
from kohpymc.discrepancy.gp import GaussianProcess
from kohpymc.discrepancy.grid import GridGP
from kohpymc.discrepancy.iid import IIDGaussian
from kohpymc.discrepancy.input_dependent import InputDependentGaussian
from kohpymc.discrepancy.none import NoDiscrepancy
from kohpymc.discrepancy.nonstationary import DecayingVariance, NonStationaryGP

__all__ = [
    "Discrepancy",
    "ModelContext",
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
]
