"""Discrepancy formulations (paper Section 3 and beyond), one module each.

Every module of this package is imported here, so a formulation written as a new module
that registers itself (``class X(Discrepancy, kind="...")``) is found by study files,
:func:`from_dict` and the contract tests without an edit anywhere else; its class is
exported from this package (and from ``kohpymc``) under its own name.
"""

import importlib
import pkgutil

from kohpymc.discrepancy.base import (
    Discrepancy,
    FormulationSpecError,
    Likelihood,
    ModelContext,
    formulation_class,
    formulation_kinds,
    from_dict,
)
from kohpymc.discrepancy.constant import ConstantBias as ConstantBias
from kohpymc.discrepancy.defaults import default_formulations
from kohpymc.discrepancy.functions import LinearBasis, ParametricFunction
from kohpymc.discrepancy.gp import GaussianProcess as GaussianProcess
from kohpymc.discrepancy.grid import GridGP as GridGP
from kohpymc.discrepancy.iid import IIDGaussian as IIDGaussian
from kohpymc.discrepancy.input_dependent import InputDependentGaussian as InputDependentGaussian
from kohpymc.discrepancy.none import NoDiscrepancy as NoDiscrepancy
from kohpymc.discrepancy.nonstationary import DecayingVariance
from kohpymc.discrepancy.nonstationary import NonStationaryGP as NonStationaryGP

# The paper's formulations are imported by name above (so type checkers see them); the loop
# imports every other module of the package, whose formulations register themselves.

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

#: the registered formulation classes, by class name
_FORMULATIONS = {cls.__name__: cls for cls in formulation_kinds().values()}
globals().update(_FORMULATIONS)

__all__ = [
    "Discrepancy",
    "FormulationSpecError",
    "Likelihood",
    "ModelContext",
    "formulation_class",
    "formulation_kinds",
    "from_dict",
    "default_formulations",
    "LinearBasis",
    "ParametricFunction",
    "DecayingVariance",
    *sorted(_FORMULATIONS),
]
