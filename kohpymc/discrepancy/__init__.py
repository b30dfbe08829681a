"""Discrepancy formulations M0–M6 (paper Section 3), one module each.

Every module of this package is imported here, so a formulation registers (and is
exported under its class name) by existing: a new ``class X(Discrepancy, kind="x")``
in a new module needs no edit elsewhere.
"""

import importlib
import pkgutil

from kohpymc.discrepancy.base import Discrepancy, ModelContext, formulation_kinds
from kohpymc.discrepancy.functions import LinearBasis, ParametricFunction
from kohpymc.discrepancy.nonstationary import DecayingVariance

for _module in sorted(m.name for m in pkgutil.iter_modules(__path__)):
    importlib.import_module(f"{__name__}.{_module}")

#: registered formulation classes defined in this package, by class name
_formulations = {
    cls.__name__: cls
    for cls in formulation_kinds().values()
    if cls.__module__.startswith(f"{__name__}.")
}
globals().update(_formulations)

__all__ = [
    "Discrepancy",
    "ModelContext",
    *sorted(_formulations),
    "DecayingVariance",
    "LinearBasis",
    "ParametricFunction",
]

del _module
