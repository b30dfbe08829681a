"""M2: iid Gaussian discrepancy, ``δ(x) ~ N(μ_δ, σ_δ²)`` (paper Section 3.2, Eqs. 6–7)."""

from __future__ import annotations

from typing import Any

from kohpymc.discrepancy.base import ModelContext
from kohpymc.discrepancy.functions import LinearBasis, MeanSpec
from kohpymc.discrepancy.independent import Component, IndependentDiscrepancy
from kohpymc.priors import HalfNormal, Prior, as_prior

__all__ = ["IIDGaussian"]


class IIDGaussian(IndependentDiscrepancy, kind="iid"):
    """M2: ``y_D ~ N(G(x; θ) + μ_δ, (σ_obs² + σ_δ²) I)``.

    Parameters
    ----------
    mean_prior : Prior, optional
        Prior of μ_δ (``"delta_mean"``); default ``Normal(0, 2 · sd(y))``.
    sd_prior : Prior, optional
        Prior of σ_δ (``"delta_sd"``); default ``HalfNormal(sd(y))``.

    Notes
    -----
    With σ_obs unknown as well, only ``σ_obs² + σ_δ²`` is identified: give the noise
    sd (known or from replicates) when you use this formulation.

    Examples
    --------
    >>> IIDGaussian().label
    'M2'
    """

    label = "M2"
    description = "iid Gaussian"

    def __init__(
        self,
        *,
        mean_prior: Prior | dict[str, Any] | None = None,
        sd_prior: Prior | dict[str, Any] | None = None,
    ) -> None:
        self.mean_prior = None if mean_prior is None else as_prior(mean_prior, name="delta_mean")
        self.sd_prior = None if sd_prior is None else as_prior(sd_prior, name="delta_sd")

    def noise_partner(self) -> tuple[str, str] | None:
        """``delta_sd``: only σ_obs² + σ_δ² enters the likelihood."""
        return ("delta_sd", "sd")

    def mean_function(self, ctx: ModelContext) -> MeanSpec:
        """The constant μ_δ, stored as the scalar ``delta_mean``."""
        return LinearBasis((), prior=self.mean_prior, scalar=True)

    def variance_function(self, ctx: ModelContext) -> Component:
        """Create ``delta_sd``; the variance is its square everywhere."""
        sd = (self.sd_prior or HalfNormal(ctx.y_scale)).create("delta_sd")
        return lambda X: sd**2 + 0.0 * X[:, 0]
