"""Pointwise log-likelihood for a multivariate-normal likelihood: exact leave-one-out.

The GP formulations (M4, M5) and every marginalized formulation have one joint
likelihood ``y ~ N(μ, K)`` per posterior draw, so the ``log_likelihood`` group would
hold one value per draw and PSIS-LOO would see a single "observation".  For a Gaussian
the leave-one-out predictive of each observation given the others is available in
closed form (Rasmussen & Williams 2006, Eq. 5.12; Sundararajan & Keerthi 2001)::

    y_i | y_-i ~ N(y_i - [K⁻¹ r]_i / [K⁻¹]_ii,  1 / [K⁻¹]_ii),   r = y - μ

and Bürkner, Gabry & Vehtari (2021, "Efficient leave-one-out cross-validation for
Bayesian non-factorized normal and Student-t models") show that these conditional
densities are the right "pointwise log-likelihood" for PSIS-LOO of a non-factorized
normal model: the importance ratios are ``1 / p(y_i | y_-i, φ)``.  Their sum is not the
joint log-likelihood; the group is marked ``attrs["pointwise"] = "loo_conditional"``.
"""

from __future__ import annotations

import arviz as az
import numpy as np
import pymc as pm
import xarray as xr

from kohpymc.gaussian import _woodbury_parts, low_rank_parts
from kohpymc.model import CalibrationModel

__all__ = [
    "compute_log_likelihood",
    "gaussian_loo_log_density",
    "loo_log_likelihood",
    "pointwise_log_likelihood",
]


def gaussian_loo_log_density(y: np.ndarray, mu: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``log p(y_i | y_-i)`` for every i under ``y ~ N(mu, cov)``.

    Parameters
    ----------
    y : array, shape (n,)
        Observations.
    mu : array, shape (..., n)
        Means (a leading batch of draws allowed).
    cov : array, shape (..., n, n)
        Covariances, symmetric positive definite.

    Returns
    -------
    numpy.ndarray, shape (..., n)
        Leave-one-out log predictive densities.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.stats import norm
    >>> y, mu = np.array([0.3, -1.0]), np.zeros(2)
    >>> out = gaussian_loo_log_density(y, mu, np.diag([1.0, 4.0]))  # independent rows
    >>> bool(np.allclose(out, norm.logpdf(y, 0.0, [1.0, 2.0])))
    True
    """
    y = np.asarray(y, dtype=float)
    mu = np.asarray(mu, dtype=float)
    cov = np.asarray(cov, dtype=float)
    n = y.shape[-1]
    if cov.shape[-2:] != (n, n) or mu.shape[-1] != n:
        raise ValueError(f"shapes do not match: y {y.shape}, mu {mu.shape}, cov {cov.shape}")
    chol = np.linalg.cholesky(cov)
    eye = np.broadcast_to(np.eye(n), cov.shape)
    chol_inv = np.linalg.solve(chol, eye)  # L⁻¹
    precision_diag = np.sum(chol_inv**2, axis=-2)  # [K⁻¹]_ii = Σ_k (L⁻¹)_ki²
    resid = y - mu
    white = np.einsum("...ij,...j->...i", chol_inv, resid)  # L⁻¹ r
    alpha = np.einsum("...ji,...j->...i", chol_inv, white)  # K⁻¹ r = L⁻ᵀ L⁻¹ r
    return 0.5 * (np.log(precision_diag) - np.log(2 * np.pi) - alpha**2 / precision_diag)


def _low_rank_loo(resid: np.ndarray, diagonal: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """:func:`gaussian_loo_log_density` for ``cov = diag(d) + F Fᵀ``, by the Woodbury identity."""
    _, alpha, precision_diag, _ = _woodbury_parts(resid, diagonal, factor)
    with np.errstate(divide="ignore"):
        return 0.5 * (np.log(precision_diag) - np.log(2 * np.pi) - alpha**2 / precision_diag)


def loo_log_likelihood(
    posterior: xr.Dataset,
    built: CalibrationModel,
    *,
    obs_dim: str = "obs",
    chunk_size: int = 500,
) -> xr.Dataset:
    """Exact leave-one-out log densities of a Gaussian likelihood per posterior draw.

    Parameters
    ----------
    posterior : xarray.Dataset
        Posterior draws with dims ``(chain, draw)`` of every free variable of the model.
    built : CalibrationModel
        The model and its formulation's record, which must give the likelihood's
        ``covariance`` (and ``mean``).
    obs_dim : str
        Name of the observation dimension of the result.
    chunk_size : int
        Draws per batched Cholesky (memory ``chunk_size · n²`` floats).  A covariance
        built by :func:`~kohpymc.gaussian.low_rank_covariance` (an emulator's ``Σ_η``)
        is not formed: ``C⁻¹ r`` and ``diag C⁻¹`` come from the Woodbury identity,
        ``O(n k²)`` per draw.

    Returns
    -------
    xarray.Dataset
        The observed variable with dims ``(chain, draw, obs_dim)``,
        ``attrs["pointwise"] = "loo_conditional"``.

    Examples
    --------
    >>> import kohpymc as kp  # doctest: +SKIP
    >>> from kohpymc.examples import beam  # doctest: +SKIP
    >>> cal = kp.calibrate(beam.physics_model(), beam.generate_data(seed=1),
    ...                    kp.GaussianProcess(["x"]), draws=100, chains=1)  # doctest: +SKIP
    >>> cal.idata.log_likelihood.attrs["pointwise"]  # doctest: +SKIP
    'loo_conditional'
    """
    record = built.likelihood
    if record.covariance is None:
        raise ValueError(
            f"{built.formulation.label or type(built.formulation).__name__}: exact "
            "leave-one-out needs the likelihood's covariance, which its record does not give"
        )
    parts = low_rank_parts(record.covariance)  # diagonal + low rank: Woodbury, O(n k²)
    fn, names = built.natural_function(
        [record.mean, record.covariance] if parts is None else [record.mean, *parts]
    )
    var_name = record.observed
    y = np.asarray(built.model.rvs_to_values[built.model[var_name]].data, dtype=float)
    n = y.size
    missing = [k for k in names if k not in posterior]
    if missing:
        raise KeyError(f"posterior lacks variable(s) {missing} needed by {var_name!r}")
    n_chain, n_draw = posterior.sizes["chain"], posterior.sizes["draw"]
    flat = {
        k: posterior[k].transpose("chain", "draw", ...).values.reshape(n_chain * n_draw, -1)
        for k in names
    }
    shapes = {k: posterior[k].shape[2:] for k in names}
    total = n_chain * n_draw
    out = np.empty((total, n))
    for start in range(0, total if parts is None else 0, chunk_size):
        stop = min(start + chunk_size, total)
        mus = np.empty((stop - start, n))
        covs = np.empty((stop - start, n, n))
        for j, d in enumerate(range(start, stop)):
            m, c = fn(*(flat[k][d].reshape(shapes[k]) for k in names))
            mus[j] = np.broadcast_to(m, (n,))
            covs[j] = c
        out[start:stop] = gaussian_loo_log_density(y, mus, covs)
    if parts is not None:
        for d in range(total):
            mean, diagonal, factor = fn(*(flat[k][d].reshape(shapes[k]) for k in names))
            out[d] = _low_rank_loo(y - np.broadcast_to(mean, (n,)), diagonal, factor)
    values = out.reshape(n_chain, n_draw, n)
    coords = {"chain": posterior["chain"].values, "draw": posterior["draw"].values}
    ds = xr.Dataset({var_name: (("chain", "draw", obs_dim), values)}, coords=coords)
    ds.attrs["pointwise"] = "loo_conditional"
    return ds


def _batched_log_likelihood(posterior: xr.Dataset, model: pm.Model) -> xr.Dataset | None:
    """PyMC's elementwise log-likelihood of every draw in one numpy evaluation, or ``None``.

    The same graph as :func:`pymc.compute_log_likelihood` (the model without value
    transforms, the observed variables' elementwise log densities), vectorised over the
    draws by :func:`kohpymc.batched_map.rows_function`: no C module to compile and no
    Python loop over draws.  ``None`` when the graph does not vectorise.
    """
    from pymc.backends.arviz import coords_and_dims_for_inferencedata, dict_to_dataset
    from pymc.model.transform.conditioning import remove_value_transforms
    from pymc.pytensorf import join_nonshared_inputs

    from kohpymc.batched_map import rows_function

    umodel = remove_value_transforms(model)
    free = list(umodel.free_RVs)
    if any(rv.name not in posterior for rv in free):
        return None
    values = [posterior[rv.name].transpose("chain", "draw", ...).values for rv in free]
    point = {umodel.rvs_to_values[rv].name: v[0, 0] for rv, v in zip(free, values, strict=True)}
    observed = list(umodel.observed_RVs)
    outputs, flat = join_nonshared_inputs(
        point=point,
        outputs=umodel.logp(vars=observed, sum=False),
        inputs=[umodel.rvs_to_values[rv] for rv in free],
        make_inputs_shared=False,
    )
    function = rows_function(flat, outputs)
    if function is None:
        return None
    n_chain, n_draw = posterior.sizes["chain"], posterior.sizes["draw"]
    rows = np.concatenate([v.reshape(n_chain * n_draw, -1) for v in values], axis=1)
    out = {
        rv.name: np.asarray(value).reshape(n_chain, n_draw, *np.shape(value)[1:])
        for rv, value in zip(observed, function(rows), strict=True)
    }
    coords, dims = coords_and_dims_for_inferencedata(umodel)
    coords = {**coords, "chain": posterior["chain"].values, "draw": posterior["draw"].values}
    return dict_to_dataset(
        out, library=pm, dims=dims, coords=coords, default_dims=["chain", "draw"],
        skip_event_dims=True,
    )  # fmt: skip


def compute_log_likelihood(idata: az.InferenceData, model: pm.Model) -> xr.Dataset:
    """:func:`pymc.compute_log_likelihood` (``extend_inferencedata=False``), batched.

    All draws in one numpy evaluation when the model's graph vectorises (the beam's
    formulations: no C module compiled, ~12 of them from an empty cache before), else
    PyMC's own loop over the draws.

    Examples
    --------
    >>> import numpy as np, pymc as pm, xarray as xr
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu")
    ...     _ = pm.Normal("y", mu, 1.0, observed=[0.0, 1.0])
    >>> post = xr.Dataset({"mu": (("chain", "draw"), [[0.0, 1.0]])})
    >>> ll = compute_log_likelihood(az.InferenceData(posterior=post), model)
    >>> np.round(ll["y"].values, 4).tolist()  # log N(y | mu, 1)
    [[[-0.9189, -1.4189], [-1.4189, -0.9189]]]
    """
    batched = _batched_log_likelihood(idata["posterior"], model)
    if batched is not None:
        return batched
    return pm.compute_log_likelihood(
        idata, model=model, extend_inferencedata=False, progressbar=False
    )


def pointwise_log_likelihood(
    idata: az.InferenceData, built: CalibrationModel, plain: CalibrationModel
) -> xr.Dataset | None:
    """Pointwise log-likelihood values for LOO, read off the formulations' records.

    ``built`` is the sampled model and ``plain`` the same formulation without
    integrated-out coefficients.  Returns ``None`` when PyMC's own log-likelihood group
    is already pointwise.

    Rows independent given the plain model's variables: PyMC's elementwise values of
    the plain model.  Else the record's own ``pointwise`` function, else the exact
    Gaussian leave-one-out conditionals from its covariance.

    Raises
    ------
    ValueError
        When the record gives none of these (naming the formulation).

    Examples
    --------
    >>> ds = pointwise_log_likelihood(cal.idata, cal.built, plain)  # doctest: +SKIP
    """
    name = built.likelihood.observed
    values = idata.log_likelihood[name] if "log_likelihood" in idata.groups() else None
    already = values is not None and values.ndim == 3
    if plain.likelihood.independent_rows:
        if already and built.likelihood.independent_rows:
            return None
        return compute_log_likelihood(idata, plain.model)
    if built.likelihood.pointwise is not None:
        return built.likelihood.pointwise(idata.posterior, built.model)
    if built.likelihood.covariance is not None:
        return loo_log_likelihood(idata.posterior, built)
    if already:
        return None
    label = built.formulation.label or type(built.formulation).__name__
    raise ValueError(
        f"{label}: no pointwise log-likelihood: its Likelihood record sets neither "
        "independent_rows, a covariance nor a pointwise function"
    )
