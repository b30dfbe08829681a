"""Shared machinery of the formulations whose δ is independent across data rows.

For M0–M3 the likelihood is the product of independent normals
``y_D,i ~ N(G(x_i; θ) + μ_δ(x_i), σ_obs² + σ_δ²(x_i))`` (paper Eqs. 5, 7, 9).  When the
mean μ_δ is linear in its coefficients with normal priors (the default), they are
integrated out analytically, ``y ~ N(G + B m0, D + B S0 Bᵀ)``, and recovered per draw
by whitening (see :meth:`~kohpymc.discrepancy.functions.LinearBasis.build_marginalized`);
the stored pointwise log-likelihood is that of the independent-normal form at the
recovered coefficients.  Predictions at new inputs draw ``δ(x*) ~ N(μ_δ(x*), σ_δ²(x*))``
independently of the calibration rows.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import pymc as pm
import pytensor.tensor as pt

from kohpymc.discrepancy.base import Discrepancy, Likelihood, ModelContext
from kohpymc.discrepancy.functions import MeanSpec, marginalizable
from kohpymc.gaussian import (
    GaussianLikelihood,
    add_to_covariance,
    covariance_solve,
    low_rank_covariance,
)

__all__ = ["IndependentDiscrepancy"]

Component = Callable[[pt.TensorVariable], pt.TensorVariable] | None


class IndependentDiscrepancy(Discrepancy):
    """Base for δ independent across rows; subclasses give mean and variance functions."""

    #: name of the mean coefficients in the model
    mean_name: ClassVar[str] = "delta_mean"
    accepts_physics_covariance = True

    def mean_function(self, ctx: ModelContext) -> MeanSpec | None:
        """The mean μ_δ as a function spec (``None``: zero mean)."""
        return None

    def variance_function(self, ctx: ModelContext) -> Component:
        """Create variance parameters; return ``σ_δ²(X)`` (``None``: no extra variance)."""
        return None

    def build(self, ctx: ModelContext) -> Likelihood:
        """Add ``y ~ N(G + μ_δ, σ_obs² + σ_δ²)``; return its record."""
        X = pt.as_tensor_variable(ctx.X)
        var_fn = self.variance_function(ctx)
        spec = self.mean_function(ctx)
        variance = ctx.noise_sd**2 if var_fn is None else ctx.noise_sd**2 + var_fn(X)
        physics_cov = ctx.physics_covariance
        if spec is not None and marginalizable(spec, ctx):
            B = spec.design(ctx, X)
            m0, s0 = spec.gaussian_prior(ctx)  # type: ignore[union-attr, misc]
            diag = variance * pt.ones_like(ctx.G)
            if physics_cov is None:
                cov = low_rank_covariance(diag, B * s0)
            else:  # low-rank when the emulator's Σ_η is (Woodbury likelihood)
                base = add_to_covariance(physics_cov, diagonal=diag)
                cov = add_to_covariance(base, factor=B * s0)
            mu = ctx.G + pt.dot(B, m0)
            GaussianLikelihood("y", mu=mu, cov=cov, observed=ctx.y, dims=ctx.obs_dim)
            if physics_cov is None:
                inv_B, inv_resid = B / diag[:, None], (ctx.y - ctx.G) / diag
            else:
                inv_B = covariance_solve(base, B)
                inv_resid = covariance_solve(base, ctx.y - ctx.G)
            mean_fn = spec.build_marginalized(  # type: ignore[union-attr]
                ctx, self.mean_name, B, inv_B, inv_resid
            )
        else:
            mean_fn = None if spec is None else spec.build(ctx, self.mean_name)
            mu = ctx.G if mean_fn is None else ctx.G + mean_fn(X)
            if physics_cov is None:
                pm.Normal("y", mu=mu, sigma=pt.sqrt(variance), observed=ctx.y, dims=ctx.obs_dim)
                cov = None
            else:  # an emulator's correlated error: rows are no longer independent
                cov = add_to_covariance(physics_cov, diagonal=variance * pt.ones_like(ctx.G))
                GaussianLikelihood("y", mu=mu, cov=cov, observed=ctx.y, dims=ctx.obs_dim)

        def predict(X_new: pt.TensorVariable, G_new: pt.TensorVariable) -> pt.TensorVariable:
            mean = G_new if mean_fn is None else G_new + mean_fn(X_new)
            if var_fn is None:
                return mean
            spread = pm.Normal("delta_random", mu=0.0, sigma=pt.sqrt(var_fn(X_new)), dims="pred")
            return mean + spread

        if cov is not None:  # coefficients integrated out or emulator error: rows correlated
            return Likelihood(predict, mean=mu, covariance=cov)
        return Likelihood(
            predict, mean=mu, variance=variance * pt.ones_like(ctx.G), independent_rows=True
        )
