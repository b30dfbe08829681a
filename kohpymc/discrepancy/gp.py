"""M4: Gaussian-process δ with a stationary squared-exponential kernel (Section 3.4).

``δ ~ GP(m(x; φ), k(x, x'))`` with ARD kernel (paper Eq. 11)
``k(x, x') = λ exp(-Σ_i (x_i - x_i')² / (2 l_i²))``, ``λ = η²``, so that
``y_D ~ N(G(X; θ) + m(X; φ), Σ + σ_obs² I)`` (Eq. 12).  Built on ``pm.gp.Marginal``
with the physics model inside the GP mean, so predictions at new inputs are the GP
conditional given the calibration data.

A user-supplied covariance replaces the SE kernel: pass
``covariance=lambda ctx, active_dims: ...`` returning any ``pm.gp.cov.Covariance``
over ``len(ctx.input_names)`` columns (create its random variables inside the
function; it is called within the model context).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pymc as pm
import pytensor.tensor as pt
from pymc.gp.util import JITTER_DEFAULT

from kohpymc.discrepancy.base import Discrepancy, Likelihood, ModelContext
from kohpymc.discrepancy.functions import LinearBasis, MeanSpec, as_function, marginalizable
from kohpymc.gaussian import GaussianLikelihood
from kohpymc.priors import HalfNormal, Prior, as_prior

__all__ = ["GaussianProcess", "CovarianceFactory", "jitter"]

#: ``factory(ctx, active_dims) -> pm.gp.cov.Covariance``
CovarianceFactory = Callable[[ModelContext, list[int]], Any]


def jitter(ctx: ModelContext) -> float:
    """The variance added to a GP covariance's diagonal, scaled to the output.

    1e-6 (PyMC's) in the output's units squared when its sd is at least 1, else 1e-6 × its
    variance.  PyMC's absolute 1e-6 is a floor of sd 1e-3 on every row's noise: on an
    output measured in units where it is ~1e-6 (a rate in mol/(L·s), a displacement in m)
    that floor is larger than the data and the GP likelihood learns nothing.  Scaled by
    the output's variance it stays 1e-6 of it; it is never larger than PyMC's.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> jitter(SimpleNamespace(y_scale=250.0)), jitter(SimpleNamespace(y_scale=1e-3))
    (1e-06, 1e-12)
    """
    return JITTER_DEFAULT * min(1.0, float(ctx.y_scale) ** 2)


def _marginal_likelihood(gp: pm.gp.Marginal, ctx: ModelContext, X: pt.TensorVariable):
    """Observe ``y ~ N(m(X), K(X) + σ_obs² I)`` as ``gp.marginal_likelihood`` would.

    Same mean and covariance, the :func:`jitter` scaled to the output, and
    ``gp.conditional`` works afterwards; the
    likelihood is :class:`~kohpymc.gaussian.GaussianLikelihood` (one LAPACK pass per
    gradient instead of PyMC's Cholesky-and-solve graph).  Returns ``(mean, cov)``.
    """
    noise = (
        pm.gp.cov.WhiteNoise(ctx.noise_sd)
        if ctx.physics_covariance is None
        else _CalibrationRowsNoise(ctx.noise_sd, ctx.physics_covariance, len(ctx.input_names))
    )
    mu, cov = gp._build_marginal_likelihood(X=X, noise_func=noise, jitter=jitter(ctx))
    gp.X, gp.y, gp.sigma = X, ctx.y, noise
    GaussianLikelihood("y", mu=mu, cov=cov, observed=ctx.y, dims=ctx.obs_dim)
    return mu, cov


class _CalibrationRowsNoise(pm.gp.cov.Covariance):
    """``σ_obs² I + Σ_η``: measurement noise plus an emulator's error, calibration rows only.

    Like ``WhiteNoise`` it is zero between different sets of rows; ``full(X)`` is only
    used on the calibration rows (the marginal likelihood and the GP conditional's
    training covariance), where ``Σ_η`` was computed.
    """

    def __init__(self, sigma, physics_cov, input_dim: int) -> None:
        super().__init__(input_dim)
        self.sigma, self.physics_cov = sigma, physics_cov

    def diag(self, X):
        return self.sigma**2 + pt.diag(self.physics_cov)

    def full(self, X, Xs=None):
        if Xs is None:
            return self.sigma**2 * pt.eye(X.shape[0]) + self.physics_cov
        return pt.zeros((X.shape[0], Xs.shape[0]))


class _KOHMean(pm.gp.mean.Mean):
    """GP mean ``G(X; θ) + m(X; φ)``."""

    def __init__(self, physics_mean, discrepancy_mean) -> None:
        super().__init__()
        self.physics_mean = physics_mean
        self.discrepancy_mean = discrepancy_mean

    def __call__(self, X):
        return self.physics_mean(X) + self.discrepancy_mean(X)


class _BasisCovariance(pm.gp.cov.Covariance):
    """``B(X) diag(s0²) B(X')ᵀ``: a linear mean with N(m0, diag(s0²)) coefficients."""

    def __init__(self, ctx: ModelContext, basis: LinearBasis, s0: np.ndarray) -> None:
        super().__init__(len(ctx.input_names))
        self.ctx, self.basis, self.s0 = ctx, basis, np.asarray(s0, dtype=float)

    def diag(self, X):
        B = self.basis.design(self.ctx, X)
        return pt.sum(B**2 * self.s0**2, axis=1)

    def full(self, X, Xs=None):
        B = self.basis.design(self.ctx, X)
        Bs = B if Xs is None else self.basis.design(self.ctx, Xs)
        return pt.dot(B * self.s0**2, Bs.T)


class GaussianProcess(Discrepancy, kind="gp"):
    """M4: GP discrepancy, stationary SE kernel with ARD length scales, parametric mean.

    Parameters
    ----------
    inputs : sequence of str
        Inputs the GP (kernel and default mean) depends on.
    mean : LinearBasis, ParametricFunction or list of names, optional
        Mean ``m(x; φ)``; default: linear in ``inputs`` with intercept
        (coefficients ``"delta_mean"``).
    amplitude_prior : Prior, optional
        Prior of η (``"delta_eta"``, ``λ = η²``); default ``HalfNormal(sd(y))``.
    lengthscale_prior : Prior, optional
        Prior of every ``l_i`` (``"delta_ls"``, dim ``"gp_input"``); default
        ``InverseGamma(4, 2 · range_i)``: mode 0.4 and mean 0.67 of the input's range,
        little mass below 0.1 of it.
    covariance : callable, optional
        ``covariance(ctx, active_dims)`` returning a ``pm.gp.cov.Covariance`` used
        instead of the SE kernel.

    Examples
    --------
    >>> GaussianProcess(["x"]).label
    'M4'
    """

    label = "M4"
    description = "stationary GP"
    study_defaults = {"inputs": "inputs"}
    code_only = ("covariance",)
    #: After the mean coefficients are integrated out, the amplitude / length-scale /
    #: physics-parameter geometry of a GP discrepancy (a long length scale lets the GP
    #: mimic smooth physics) still needs smaller steps: 0.9 left 1-3 divergences in 4000
    #: draws on the beam, 0.95 none (seeds 2026, 1, 2).
    default_target_accept = 0.95
    accepts_physics_covariance = True

    def __init__(
        self,
        inputs: Sequence[str],
        mean: MeanSpec | Sequence[str] | None = None,
        *,
        amplitude_prior: Prior | dict[str, Any] | None = None,
        lengthscale_prior: Prior | dict[str, Any] | None = None,
        covariance: CovarianceFactory | None = None,
    ) -> None:
        if isinstance(inputs, str):
            inputs = [inputs]
        self.gp_inputs = tuple(inputs)
        if not self.gp_inputs:
            raise ValueError(f"{type(self).__name__}: give at least one input for the kernel")
        self.mean = as_function(list(self.gp_inputs) if mean is None else mean, offset=0.0)
        self.amplitude_prior = (
            None if amplitude_prior is None else as_prior(amplitude_prior, name="delta_eta")
        )
        self.lengthscale_prior = (
            None if lengthscale_prior is None else as_prior(lengthscale_prior, name="delta_ls")
        )
        self.covariance_factory = covariance

    @property
    def inputs(self) -> tuple[str, ...]:
        """Inputs of the kernel and the mean."""
        return tuple(dict.fromkeys(self.gp_inputs + self.mean.inputs))

    def hyperparameters(self, ctx: ModelContext) -> tuple[Any, Any]:
        """Create ``delta_eta`` and ``delta_ls`` (one length scale per kernel input)."""
        model = pm.modelcontext(None)
        model.add_coord("gp_input", list(self.gp_inputs))
        if self.lengthscale_prior is not None:
            ls = self.lengthscale_prior.create("delta_ls", dims="gp_input")
        else:
            spans = np.array([ctx.span[k] for k in self.gp_inputs])
            ls = pm.InverseGamma("delta_ls", alpha=4.0, beta=2.0 * spans, dims="gp_input")
        eta = (self.amplitude_prior or HalfNormal(ctx.y_scale)).create("delta_eta")
        return eta, ls

    def stationary_kernel(self, ctx: ModelContext, active_dims: list[int]):
        """``η² · ExpQuad(ls)`` over ``active_dims`` (creates ``delta_eta``, ``delta_ls``)."""
        eta, ls = self.hyperparameters(ctx)
        d = len(ctx.input_names)
        return eta**2 * pm.gp.cov.ExpQuad(d, ls=ls, active_dims=active_dims)

    def kernel(self, ctx: ModelContext, active_dims: list[int]):
        """The covariance function of δ (subclasses add terms)."""
        if self.covariance_factory is not None:
            return self.covariance_factory(ctx, active_dims)
        return self.stationary_kernel(ctx, active_dims)

    def build(self, ctx: ModelContext) -> Likelihood:
        """Marginal GP likelihood ``N(G + m, K + σ_obs² I)``; predictor is the conditional.

        With a linear mean whose coefficients have normal priors (the default) the
        coefficients are integrated into the covariance, ``K + B S0 Bᵀ`` with mean
        ``G + B m0`` (Rasmussen & Williams 2006, §2.7), and recovered per draw as the
        deterministic ``delta_mean``.
        """
        active = [ctx.column(k) for k in self.gp_inputs]
        X = pt.as_tensor_variable(ctx.X)
        cov = self.kernel(ctx, active)
        spec = self.mean
        if marginalizable(spec, ctx):
            m0, s0 = spec.gaussian_prior(ctx)  # type: ignore[union-attr, misc]
            basis_cov = _BasisCovariance(ctx, spec, s0)  # type: ignore[arg-type]
            prior_mean = lambda Xt: pt.dot(spec.design(ctx, Xt), m0)  # noqa: E731
            gp = pm.gp.Marginal(
                mean_func=_KOHMean(ctx.physics_mean, prior_mean), cov_func=cov + basis_cov
            )
            mu, total = _marginal_likelihood(gp, ctx, X)
            B = spec.design(ctx, X)  # type: ignore[union-attr]
            c0 = cov(X) + (ctx.noise_sd**2 + jitter(ctx)) * pt.eye(ctx.X.shape[0])
            if ctx.physics_covariance is not None:
                c0 = c0 + ctx.physics_covariance
            chol = pt.linalg.cholesky(c0)
            spec.build_marginalized(  # type: ignore[union-attr]
                ctx,
                "delta_mean",
                B,
                pt.linalg.cho_solve((chol, True), B),
                pt.linalg.cho_solve((chol, True), ctx.y - ctx.G),
            )
        else:
            mean_fn = spec.build(ctx, "delta_mean")
            gp = pm.gp.Marginal(mean_func=_KOHMean(ctx.physics_mean, mean_fn), cov_func=cov)
            mu, total = _marginal_likelihood(gp, ctx, X)

        def predict(X_new: pt.TensorVariable, G_new: pt.TensorVariable) -> pt.TensorVariable:
            del G_new  # the GP mean evaluates the physics at X_new itself
            return gp.conditional("gp_conditional", X_new, dims="pred", jitter=jitter(ctx))

        return Likelihood(predict, mean=mu, covariance=total)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(inputs={list(self.gp_inputs)}, mean={self.mean})"
