"""M1: constant bias, ``δ(x) = b`` (paper Section 3.1, Eq. 5)."""

from __future__ import annotations

from typing import Any

from kohpymc.discrepancy.base import ModelContext
from kohpymc.discrepancy.functions import LinearBasis, MeanSpec
from kohpymc.discrepancy.independent import IndependentDiscrepancy
from kohpymc.priors import Prior, as_prior

__all__ = ["ConstantBias"]


class ConstantBias(IndependentDiscrepancy, kind="constant"):
    """M1: ``y_D ~ N(G(x; θ) + b, σ_obs² I)`` with an unknown constant ``b``.

    Parameters
    ----------
    prior : Prior, optional
        Prior of ``b`` (variable ``"delta"``); default ``Normal(0, 2 · sd(y))``.  With
        a normal prior ``b`` is integrated out of the likelihood and recovered per draw.

    Examples
    --------
    >>> from kohpymc import Uniform
    >>> ConstantBias(prior=Uniform(-5, 5)).label
    'M1'
    """

    label = "M1"
    description = "constant bias"
    mean_name = "delta"

    def __init__(self, *, prior: Prior | dict[str, Any] | None = None) -> None:
        self.prior = None if prior is None else as_prior(prior, name="delta")

    def mean_function(self, ctx: ModelContext) -> MeanSpec:
        """An intercept-only basis stored as the scalar ``delta``."""
        return LinearBasis((), prior=self.prior, scalar=True)
