r"""M4 on a full grid with replicates: the exact GP likelihood by Kronecker algebra.

When the calibration inputs lie on a full grid (every combination of the unique values
of each kernel input) with the same number ``r`` of replicates per grid point, the
stationary SE-kernel GP of :class:`~kohpymc.discrepancy.gp.GaussianProcess` has an exact
likelihood that never forms the ``n × n`` covariance (``benchmarks/scale.py``; the
linear algebra lives in :mod:`kohpymc.kronecker`):

1. **Replicate reduction.**  With ``ȳ``, ``Ḡ`` the replicate means on the ``m = n / r``
   grid points and ``s² = σ²/r``,
   ``p(y) = N(ȳ | Ḡ + m0, K + c 11ᵀ + s² I) · C``,
   ``log C = Σ_u [-(r-1)/2 log(2πσ²) - ½ log r - S_u / (2σ²)]`` with ``S_u`` the
   within-replicate sum of squares of the residual.  ``C`` involves neither θ nor the
   GP, and the model's log density is that of the raw data.
2. **Kronecker.**  ``K = η² ⊗_k K_k(ℓ_k)``; with ``K_k = Q_k diag(λ_k) Q_kᵀ`` the solve
   and the log-determinant of ``K + s² I`` are diagonal in the basis ``⊗_k Q_k``.  The
   constant discrepancy mean, integrated out as in ``GaussianProcess`` (``c = s0²``, the
   prior variance of the intercept), is a rank-one update (Sherman–Morrison and the
   matrix-determinant lemma).
3. **Gradient.**  The log density is an inlined ``OpFromGraph`` whose ``lop_overrides``
   give the analytic gradient ``½ (α'ᵀ ∂K α' - tr((K' + s² I)⁻¹ ∂K))`` in the eigenbasis,
   so PyTensor never differentiates through ``eigh``.

Like ``GaussianProcess`` the noise variance carries its jitter
(``σ² → σ² + jitter``, :func:`kohpymc.discrepancy.gp.jitter`), so both give the same log density.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import xarray as xr
from pymc.model.transform.conditioning import remove_value_transforms
from pytensor.graph.basic import Constant
from pytensor.graph.traversal import ancestors

from kohpymc.discrepancy.base import Likelihood, ModelContext
from kohpymc.discrepancy.functions import LinearBasis, marginalizable
from kohpymc.discrepancy.gp import GaussianProcess, jitter
from kohpymc.kronecker import (
    GridLayout,
    KronSolver,
    grid_layout,
    grid_loo_log_density,
    kron_gp_loglik,
)
from kohpymc.priors import Prior

__all__ = ["GridGP"]


class GridGP(GaussianProcess, kind="grid_gp"):
    """M4 on gridded data: exact Kronecker GP likelihood with replicate reduction.

    The same model as :class:`~kohpymc.discrepancy.gp.GaussianProcess` with the default
    squared-exponential ARD kernel (same parameters ``delta_eta``, ``delta_ls`` and
    priors) for data whose rows, restricted to the kernel inputs, form a full grid with
    an equal number of replicates per point.  The cost is a few small ``eigh`` per
    gradient instead of an ``n × n`` Cholesky.

    Parameters
    ----------
    inputs : sequence of str
        Kernel inputs; every model input (the physics inputs) must be one of them.
    mean : list, LinearBasis or "zero", optional
        ``[]`` (default) or an intercept-only :class:`LinearBasis`: a constant mean as
        ``GaussianProcess(inputs, mean=[])`` (integrated out when its prior is normal,
        recovered as ``delta_mean``); ``"zero"``: no discrepancy mean.  Other means
        raise ``ValueError``.
    amplitude_prior, lengthscale_prior : Prior, optional
        As in :class:`GaussianProcess`.

    Notes
    -----
    * σ_obs must be known (data with ``noise_sd``); an unknown σ_obs raises
      ``ValueError``.
    * The observed ``"y"`` is a :class:`pymc.CustomDist` with a joint (not elementwise)
      log density (``pm.compute_log_likelihood`` gives one value per draw);
      :func:`kohpymc.calibrate` replaces it by the exact leave-one-out conditionals of
      :meth:`pointwise_log_likelihood`, as for ``GaussianProcess``.  It has no random
      draws (prior/posterior predictive of ``"y"`` itself is unavailable; use
      :func:`kohpymc.predict`).
    * Predictions draw each point of the GP conditional independently (its marginal
      mean and variance), not jointly as ``GaussianProcess`` does.

    Examples
    --------
    >>> GridGP(["x", "P"]).label
    'M4'
    """

    label = "M4"
    description = "stationary GP (grid/Kronecker)"

    # one noise sd for all rows (the Kronecker algebra): an emulator's error cannot enter
    accepts_physics_covariance = False

    def __init__(
        self,
        inputs: Sequence[str],
        mean: LinearBasis | Sequence[str] | str | None = (),
        *,
        amplitude_prior: Prior | dict[str, Any] | None = None,
        lengthscale_prior: Prior | dict[str, Any] | None = None,
    ) -> None:
        zero = isinstance(mean, str) and mean == "zero"
        super().__init__(
            inputs,
            [] if zero or mean is None else mean,
            amplitude_prior=amplitude_prior,
            lengthscale_prior=lengthscale_prior,
        )
        self.zero_mean = zero
        spec = self.mean
        if not (isinstance(spec, LinearBasis) and spec.intercept and not spec.products):
            raise ValueError(
                f"GridGP supports a zero mean ('zero') or a constant mean ([] or an "
                f"intercept-only LinearBasis), got {spec!r}"
            )

    @property
    def inputs(self) -> tuple[str, ...]:
        """Kernel inputs."""
        return self.gp_inputs

    def _check(self, ctx: ModelContext) -> tuple[GridLayout, float]:
        outside = [k for k in ctx.input_names if k not in self.gp_inputs]
        if outside:
            raise ValueError(
                f"GridGP: model input(s) {outside} are not kernel inputs "
                f"{list(self.gp_inputs)}; the physics would vary within a grid cell"
            )
        if ctx.measurement_sd is not None:
            raise ValueError(
                "GridGP needs one noise sd for all rows; an emulated physics model adds "
                "its own variance per row (use GaussianProcess instead)"
            )
        if not isinstance(ctx.noise_sd, Constant):
            raise ValueError(
                "GridGP needs a known noise sd (give the data a noise_sd or replicates); "
                "σ_obs is unknown here"
            )
        sigma = float(np.asarray(ctx.noise_sd.data))
        cols = [ctx.column(k) for k in self.gp_inputs]
        return grid_layout(ctx.X[:, cols], self.gp_inputs), sigma

    def build(self, ctx: ModelContext) -> Likelihood:
        """Exact replicate-reduced Kronecker likelihood ``"y"``; predictor as the GP's.

        Raises
        ------
        ValueError
            Data off a full grid, unequal replicates, a model input outside the kernel,
            or an unknown noise sd.
        """
        layout, sigma = self._check(ctx)
        shape, r, m, order = layout.shape, layout.replicates, layout.size, layout.order
        axes = layout.axes
        var = sigma**2 + jitter(ctx)  # noise plus the GP's jitter
        s2 = var / r
        eta, ls = self.hyperparameters(ctx)
        spec = self.mean
        X = pt.as_tensor_variable(ctx.X)
        c = 0.0
        m0 = 0.0
        if self.zero_mean:
            mean_raw = pt.zeros_like(ctx.G)
        elif marginalizable(spec, ctx):
            m0s, s0s = spec.gaussian_prior(ctx)  # type: ignore[union-attr, misc]
            m0, c = float(m0s[0]), float(s0s[0]) ** 2
            mean_raw = pt.zeros_like(ctx.G) + m0
        else:
            mean_raw = spec.build(ctx, "delta_mean")(X)
        mu = ctx.G + mean_raw

        def logp(value, mu, eta, ls):
            Rr = (value - mu)[order].reshape((*shape, r))
            Rbar = pt.mean(Rr, axis=-1)
            ss = pt.sum((Rr - Rbar[..., None]) ** 2)
            const = -0.5 * (r - 1) * m * np.log(2 * np.pi * var) - 0.5 * m * np.log(r)
            return kron_gp_loglik(Rbar, axes, eta, ls, s2, c) + const - ss / (2 * var)

        info = {"layout": layout, "noise_var": var, "c": c}
        pm.CustomDist(
            "y",
            mu,
            eta,
            ls,
            logp=logp,
            signature="(n),(),(k)->(n)",
            observed=ctx.y,
            dims=ctx.obs_dim,
        )
        solver = KronSolver(axes, eta, ls, s2, c)
        y_bar = np.mean(np.asarray(ctx.y, dtype=float)[order].reshape(m, r), axis=1)
        G_bar = pt.mean(ctx.G[order].reshape((m, r)), axis=1)
        if c > 0:
            resid = (y_bar - G_bar).reshape((1, *shape))
            spec.build_marginalized(  # type: ignore[union-attr]
                ctx,
                "delta_mean",
                pt.ones((m, 1)),
                solver._solve0(pt.ones((1, *shape))).reshape((m, 1)),
                solver._solve0(resid).reshape((m,)),
            )
        mean_bar = pt.mean(mean_raw[order].reshape((m, r)), axis=1)
        alpha = solver.solve((y_bar - G_bar - mean_bar).reshape((1, *shape)))[0]
        kernel_cols = [ctx.column(k) for k in self.gp_inputs]

        def predict(X_new: pt.TensorVariable, G_new: pt.TensorVariable) -> pt.TensorVariable:
            # the mean is constant, so m(X_new) is that constant (its value at any row)
            mean_new = pt.zeros_like(G_new) + (mean_raw[0] if not self.zero_mean else 0.0)
            Ks = solver.cross([X_new[:, j] for j in kernel_cols])  # (p, *grid)
            Kc = Ks + c if c > 0 else Ks
            axes_sum = tuple(range(1, len(shape) + 1))
            cond_mean = G_new + mean_new + pt.sum(Kc * alpha, axis=axes_sum)
            prior_var = eta**2 + c
            cond_var = prior_var - pt.sum(Kc * solver.solve(Kc), axis=axes_sum)
            sd = pt.sqrt(pt.maximum(cond_var, 0.0) + jitter(ctx))
            return pm.Normal("gp_conditional", mu=cond_mean, sigma=sd, dims="pred")

        def pointwise(posterior: xr.Dataset, model: pm.Model) -> xr.Dataset:
            return self.pointwise_log_likelihood(posterior, model, info)

        return Likelihood(predict, mean=mu, pointwise=pointwise)

    def pointwise_log_likelihood(
        self,
        posterior: xr.Dataset,
        model: pm.Model,
        info: dict[str, Any],
        var_name: str = "y",
        *,
        obs_dim: str = "obs",
    ) -> xr.Dataset:
        """Exact leave-one-out log densities per draw (as :func:`kohpymc.loo.loo_log_likelihood`).

        ``model`` must have been built with this formulation and ``info`` is the grid
        layout, noise variance and mean-prior variance of that build (the record's
        ``pointwise`` passes them); see :func:`grid_loo_log_density`.

        Examples
        --------
        >>> ds = cal.likelihood.pointwise(cal.idata.posterior, cal.model)  # doctest: +SKIP
        >>> ds["y"].dims  # doctest: +SKIP
        ('chain', 'draw', 'obs')
        """
        umodel = remove_value_transforms(model)
        rv = umodel[var_name]
        outs = umodel.replace_rvs_by_values(list(rv.owner.inputs[2:5]))  # mu, eta, ls
        needed = [v for v in umodel.value_vars if v in ancestors(outs)]
        fn = pytensor.function(needed, outs, on_unused_input="ignore")
        observed = umodel.rvs_to_values[rv]
        raw = observed.get_value() if hasattr(observed, "get_value") else observed.data
        y = np.asarray(raw, dtype=float)
        names = [v.name for v in needed]
        n_chain, n_draw = posterior.sizes["chain"], posterior.sizes["draw"]
        flat = {
            k: posterior[k]
            .transpose("chain", "draw", ...)
            .values.reshape(n_chain * n_draw, *posterior[k].shape[2:])
            for k in names
        }
        out = np.empty((n_chain * n_draw, y.size))
        for d in range(n_chain * n_draw):
            mu, eta, ls = fn(*(flat[k][d] for k in names))
            out[d] = grid_loo_log_density(
                y,
                np.broadcast_to(mu, y.shape),
                float(eta),
                np.asarray(ls),
                info["layout"],
                info["noise_var"],
                info["c"],
            )
        coords = {"chain": posterior["chain"].values, "draw": posterior["draw"].values}
        values = out.reshape(n_chain, n_draw, y.size)
        ds = xr.Dataset({var_name: (("chain", "draw", obs_dim), values)}, coords=coords)
        ds.attrs["pointwise"] = "loo_conditional"
        return ds

    def __repr__(self) -> str:
        mean = "'zero'" if self.zero_mean else repr(self.mean)
        return f"{type(self).__name__}(inputs={list(self.gp_inputs)}, mean={mean})"
