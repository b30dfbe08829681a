"""The default formulation sets of studies (paper Section 6): M0–M4, M5 with a time input."""

from __future__ import annotations

from collections.abc import Sequence

from kohpymc.discrepancy.base import Discrepancy
from kohpymc.discrepancy.constant import ConstantBias
from kohpymc.discrepancy.gp import GaussianProcess
from kohpymc.discrepancy.iid import IIDGaussian
from kohpymc.discrepancy.input_dependent import InputDependentGaussian
from kohpymc.discrepancy.none import NoDiscrepancy
from kohpymc.discrepancy.nonstationary import NonStationaryGP

__all__ = ["default_formulations"]


def default_formulations(
    inputs: Sequence[str], *, time: str | None = None
) -> dict[str, Discrepancy]:
    """M0–M4 with means (and M3's log-variance) linear in ``inputs``; M5 if ``time`` given.

    Examples
    --------
    >>> list(default_formulations(["x"]))
    ['M0', 'M1', 'M2', 'M3', 'M4']
    >>> list(default_formulations(["V", "t"], time="t"))[-1]
    'M5'
    """
    inputs = list(inputs)
    out: dict[str, Discrepancy] = {
        "M0": NoDiscrepancy(),
        "M1": ConstantBias(),
        "M2": IIDGaussian(),
        "M3": InputDependentGaussian(mean=inputs),
        "M4": GaussianProcess(inputs),
    }
    if time is not None:
        out["M5"] = NonStationaryGP(inputs, time=time)
    return out
