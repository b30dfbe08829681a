r"""M6: scaled Gaussian stochastic process δ (S-GaSP; Gu & Wang 2018).

The S-GaSP is a GP ``δ ~ GP(0, σ_δ² r(·,·))`` conditioned to have a small L2 norm
``Z = ∫ δ(x)² dx``: with a density ``p_Z(z) ∝ exp(-λ_z z / (2 σ_δ²))`` on ``Z``, the
process puts most of the output on the physics, so θ is pulled towards the L2-best
value ``argmin_θ ∫ (ζ(x) - G(x; θ))² dx`` (the physics closest to reality).
Discretising ``Z ≈ (1/n) Σ_i δ(x_i)²`` on the ``n`` calibration inputs ``X`` gives
the density ``N(δ_X; 0, K) · exp(-λ_z/(2 n σ_δ²) δ_Xᵀ δ_X)`` (Gu & Wang 2018, Sec. 3),
i.e. the covariance at the calibration inputs

.. math::

    K_z = (K^{-1} + \tfrac{\lambda_z}{n \sigma_\delta^2} I)^{-1}
        = K - K (K + c I)^{-1} K, \qquad c = n \sigma_\delta^2 / \lambda_z,

and, for any inputs ``x, x'`` (the same conditioning applied to the joint prior of
``X`` and the new points, as RobustCalibration's ``Get_R_z_new`` / ``predict``),

.. math::

    k_z(x, x') = k(x, x') - k(x, X) (K + c I)^{-1} k(X, x').

This is the GP conditioned on "pseudo-observations" ``0 = δ(x_i) + e_i`` with
``e_i ~ N(0, c)``; it is what :class:`SGaSPCovariance` computes, so the likelihood
``y ~ N(G + m, K_z + σ_obs² I)`` and the predictions at new inputs (the GP
conditional under ``k_z``) come from the M4 machinery unchanged.  ``λ_z → 0`` gives
M4 back; ``λ_z → ∞`` forces δ to zero at the calibration inputs.

Default ``λ_z`` (RobustCalibration 0.5.6, ``R/functions.R``, "inverse proportional to
gamma"): ``λ_z = sqrt(n · ‖β ⊙ L‖₂ / η)`` with ``β_i`` the inverse range parameters
of the kernel, ``L_i`` the range of input ``i`` over the calibration data and
``η = σ_obs² / σ_δ²`` the nugget ratio.  For our kernel
``exp(-Σ (x_i - x_i')² / (2 l_i²))`` (the package's ``pow_exp`` with ``α = 2``),
``β_i = 1 / (√2 l_i)``; λ_z is then a deterministic function of the sampled
``delta_eta``, ``delta_ls`` (and σ_obs), recorded as ``"delta_lambda_z"``.

The S-GaSP penalises the GP part of δ only: a discrepancy mean ``m(x; φ)`` (absent by
default here, as ``have_trend = FALSE`` in RobustCalibration) is not shrunk, and a
mean that can mimic the physics (e.g. linear in the input of ``G = θ x``) confounds θ
again.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pymc as pm
import pytensor.tensor as pt

from kohpymc.discrepancy.base import ModelContext
from kohpymc.discrepancy.functions import MeanSpec, ParametricFunction
from kohpymc.discrepancy.gp import GaussianProcess
from kohpymc.priors import Prior, as_prior

__all__ = ["ScaledGP", "SGaSPCovariance", "default_lambda_z"]


class SGaSPCovariance(pm.gp.cov.Covariance):
    r"""Discretised S-GaSP covariance of a base kernel on reference inputs ``X``.

    .. math::

        k_z(x, x') = k(x, x') - k(x, X) (k(X, X) + c I)^{-1} k(X, x')

    (Gu & Wang 2018; ``c = n σ_δ² / λ_z``).  At ``X`` it equals
    ``(K⁻¹ + I / c)⁻¹``; it is positive semi-definite for ``c > 0`` and tends to
    ``k`` as ``c → ∞``.

    Parameters
    ----------
    base : pymc.gp.cov.Covariance
        The GaSP kernel ``k`` (``σ_δ² r``).
    X_ref : array-like
        ``(n, d)`` inputs where ``Z`` is discretised (the calibration inputs).
    pseudo_variance : tensor-like
        ``c = n σ_δ² / λ_z > 0``.

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> X = np.linspace(0, 1, 4)[:, None]
    >>> base = pm.gp.cov.ExpQuad(1, ls=0.3)
    >>> Kz = SGaSPCovariance(base, X, 0.5)(X).eval()
    >>> K = base(X).eval()
    >>> bool(np.allclose(Kz, np.linalg.inv(np.linalg.inv(K) + np.eye(4) / 0.5)))
    True
    """

    def __init__(self, base: pm.gp.cov.Covariance, X_ref: Any, pseudo_variance: Any) -> None:
        super().__init__(base.input_dim)
        self.base = base
        self.X_ref = pt.as_tensor_variable(np.asarray(X_ref, dtype=float))
        self.pseudo_variance = pt.as_tensor_variable(pseudo_variance)

    def _whitened(self, X):
        """``L⁻¹ k(X_ref, X)`` with ``L Lᵀ = k(X_ref, X_ref) + c I``."""
        n = self.X_ref.shape[0]
        chol = pt.linalg.cholesky(self.base(self.X_ref) + self.pseudo_variance * pt.eye(n))
        return pt.linalg.solve_triangular(chol, self.base(self.X_ref, X), lower=True)

    def full(self, X, Xs=None):  # noqa: D102
        A = self._whitened(X)
        if Xs is None:
            return self.base(X) - pt.dot(A.T, A)
        return self.base(X, Xs) - pt.dot(A.T, self._whitened(Xs))

    def diag(self, X):  # noqa: D102
        return self.base(X, diag=True) - pt.sum(self._whitened(X) ** 2, axis=0)


def default_lambda_z(n: int, spans: Any, lengthscales: Any, eta: Any, noise_sd: Any) -> Any:
    r"""RobustCalibration's default ``λ_z = sqrt(n ‖β ⊙ L‖₂ σ_δ² / σ_obs²)``.

    ``β_i = 1 / (√2 l_i)`` (inverse range of the SE kernel written as
    ``exp(-(β d)²)``), ``L_i`` the input spans, ``σ_δ = eta``.

    Examples
    --------
    >>> lam = default_lambda_z(20, [1.0], [1 / np.sqrt(2)], 1.0, 1.0)
    >>> round(float(lam.eval()), 4)  # sqrt(20)
    4.4721
    """
    beta_span = pt.as_tensor_variable(spans) / (np.sqrt(2.0) * pt.as_tensor_variable(lengthscales))
    return pt.sqrt(n * pt.sqrt(pt.sum(beta_span**2)) * eta**2 / noise_sd**2)


#: zero discrepancy mean (the S-GaSP default)
_ZERO_MEAN = ParametricFunction(lambda inputs, params: 0.0, {}, inputs=())


class ScaledGP(GaussianProcess, kind="scaled_gp"):
    """M6: scaled GP (S-GaSP) discrepancy: SE ARD kernel shrunk in L2 norm.

    Parameters
    ----------
    inputs : sequence of str
        Inputs of the kernel.
    mean : LinearBasis, ParametricFunction or list of names, optional
        Discrepancy mean ``m(x; φ)``; default zero (a mean is not shrunk by the
        S-GaSP, see the module docstring).
    amplitude_prior, lengthscale_prior : Prior, optional
        As for :class:`~kohpymc.discrepancy.gp.GaussianProcess` (``delta_eta``,
        ``delta_ls``).
    lambda_z : float or Prior, optional
        The scaling ``λ_z ≥ 0``: a value (``0`` is M4's GaSP), a prior (random variable
        ``"delta_lambda_z"``), or ``None`` for RobustCalibration's default
        (:func:`default_lambda_z`, recorded as the deterministic ``"delta_lambda_z"``).

    Examples
    --------
    >>> from kohpymc.discrepancy.base import from_dict
    >>> m6 = from_dict({"type": "scaled_gp"}, inputs=["x"])
    >>> m6.label, m6.inputs, m6.to_dict()
    ('M6', ('x',), {'type': 'scaled_gp', 'inputs': ['x']})
    """

    label = "M6"
    description = "scaled GP (S-GaSP)"
    study_defaults = {"inputs": "inputs"}
    code_only = ()

    def __init__(
        self,
        inputs: Sequence[str],
        mean: MeanSpec | Sequence[str] | None = None,
        *,
        amplitude_prior: Prior | dict[str, Any] | None = None,
        lengthscale_prior: Prior | dict[str, Any] | None = None,
        lambda_z: float | Prior | dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            inputs,
            mean,
            amplitude_prior=amplitude_prior,
            lengthscale_prior=lengthscale_prior,
        )
        if mean is None:
            self.mean = _ZERO_MEAN
        self.lambda_z: float | Prior | None
        if lambda_z is None or isinstance(lambda_z, Prior):
            self.lambda_z = lambda_z
        elif isinstance(lambda_z, dict):
            self.lambda_z = as_prior(lambda_z, name="delta_lambda_z")
        else:
            value = float(lambda_z)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"lambda_z must be finite and >= 0, got {lambda_z!r}")
            self.lambda_z = value

    def __repr__(self) -> str:
        args = self.__dict__.get("_init_arguments", {})
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in args.items())})"

    def kernel(self, ctx: ModelContext, active_dims: list[int]):
        """The S-GaSP covariance of ``η² ExpQuad(ls)`` on the calibration inputs."""
        eta, ls = self.hyperparameters(ctx)
        base = eta**2 * pm.gp.cov.ExpQuad(len(ctx.input_names), ls=ls, active_dims=active_dims)
        n = ctx.X.shape[0]
        if self.lambda_z is None:
            spans = np.array([ctx.span[k] for k in self.gp_inputs])
            lam = pm.Deterministic(
                "delta_lambda_z", default_lambda_z(n, spans, ls, eta, ctx.sigma_obs)
            )
        elif isinstance(self.lambda_z, Prior):
            lam = self.lambda_z.create("delta_lambda_z")
        elif self.lambda_z == 0.0:
            return base
        else:
            lam = self.lambda_z
        return SGaSPCovariance(base, ctx.X, n * eta**2 / lam)
