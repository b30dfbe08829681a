"""M0: no discrepancy, ``y_D = G(x; θ) + ε``."""

from __future__ import annotations

from kohpymc.discrepancy.independent import IndependentDiscrepancy

__all__ = ["NoDiscrepancy"]


class NoDiscrepancy(IndependentDiscrepancy, kind="none"):
    """M0: the physics model alone, ``y_D ~ N(G(x; θ), σ_obs²)``.

    Examples
    --------
    >>> NoDiscrepancy().label
    'M0'
    """

    label = "M0"
    description = "no discrepancy"
