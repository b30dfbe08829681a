r"""Identifiability of every parameter from the expected Fisher information.

The expected Fisher information of the full Gaussian likelihood ``y ~ N(μ(ψ), Σ(ψ))``
of a formulation, ``I_ij = ∂_i μᵀ Σ⁻¹ ∂_j μ + ½ tr(Σ⁻¹ ∂_iΣ Σ⁻¹ ∂_jΣ)``, includes the
variance and GP covariance parameters (beyond the paper's Taylor check); its rank and
conditioning get the same treatment as the sensitivity matrix.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from kohpymc.identifiability.model_check import (
    _design_point,
    _flat_point,
    _free_names,
    _jacobians,
    _likelihood_parts,
    regular,
)
from kohpymc.identifiability.rank import IdentifiabilityReport, analyse_matrix
from kohpymc.model import compose_model

__all__ = ["fisher_information_check"]


def fisher_information_check(
    physics: Any,
    data: Any,
    discrepancy: Any = None,
    *,
    point: Mapping[str, Any] | str | None = None,
    rtol: float = 1e-6,
) -> IdentifiabilityReport:
    """Rank and conditioning of the expected Fisher information of the full likelihood.

    For ``y ~ N(μ(ψ), Σ(ψ))`` over *all* parameters ψ (physics, discrepancy mean,
    variance and GP covariance parameters, σ_obs when calibrated):

    ``I_ij = ∂_i μᵀ Σ⁻¹ ∂_j μ + ½ tr(Σ⁻¹ ∂_iΣ Σ⁻¹ ∂_jΣ)``.

    The report analyses a square root ``R`` of ``I`` (``RᵀR = I``), computed from the
    correlation form ``C = D⁻¹ I D⁻¹ = V Λ Vᵀ`` (``D = diag(√I_jj)``) as
    ``R = Λ^{1/2} Vᵀ D``; its rank is that of ``I`` and its null directions, in the
    parameters' own units, are the combinations the likelihood cannot resolve, e.g. a GP
    amplitude and the noise sd when the length scale is far below the data spacing, or
    σ_obs and σ_δ of M2, which enter only as ``σ_obs² + σ_δ²`` (null direction
    ``Δσ_obs : Δσ_δ = σ_δ : -σ_obs``).  ``rtol`` applies to singular values of the
    column-scaled ``R`` (square roots of eigenvalues of ``C``), so 1e-6 means 1e-12 on
    ``C``.

    Examples
    --------
    >>> from kohpymc import GaussianProcess
    >>> from kohpymc.examples import beam
    >>> report = fisher_information_check(beam.physics_model(), beam.generate_data(),
    ...                                   GaussianProcess(["x"]))
    >>> report.kind
    'fisher'
    """
    if data.n > 2000:
        raise ValueError(f"the dense Fisher information needs n <= 2000 rows, got {data.n}")
    built = compose_model(physics, data, discrepancy, marginalize=False)
    model = built.model
    mu, second, is_mv = _likelihood_parts(built)
    start = model.initial_point()
    values = _design_point(model, point, start)
    rvs = list(model.free_RVs)
    entries = _free_names(model, rvs, start)
    (mu_val, J), (s_val, dS) = _jacobians(model, [mu, second], rvs, values)
    if point is None and not _finite(mu_val, J, s_val, dS):
        # a model undefined at the prior centre (on_nonfinite="reject"): a finite point
        for name, value in regular(physics, data)().items():
            values[name] = np.asarray(value, dtype=float).reshape(values[name].shape)
        (mu_val, J), (s_val, dS) = _jacobians(model, [mu, second], rvs, values)
    if not _finite(mu_val, J, s_val, dS):
        raise ValueError("the likelihood's mean or covariance is non-finite at the expansion point")
    n = data.n
    p = len(entries)
    if is_mv:
        cov = s_val.reshape(n, n)
        dcov = dS.reshape(n, n, p)
    else:
        sd = np.broadcast_to(s_val, (n,)) if s_val.size == 1 else s_val
        dsd = np.broadcast_to(dS, (n, p)) if dS.shape[0] == 1 else dS
        cov = np.diag(sd**2)
        dcov = np.zeros((n, n, p))
        idx = np.arange(n)
        dcov[idx, idx, :] = 2.0 * sd[:, None] * dsd
    J = np.broadcast_to(J, (n, p)) if J.shape[0] == 1 else J
    chol = np.linalg.cholesky(cov)
    cinv_J = np.linalg.solve(chol.T, np.linalg.solve(chol, J))
    info = J.T @ cinv_J
    cinv_dS = [np.linalg.solve(chol.T, np.linalg.solve(chol, dcov[:, :, k])) for k in range(p)]
    for i in range(p):
        for j in range(i, p):
            t = 0.5 * np.sum(cinv_dS[i] * cinv_dS[j].T)
            info[i, j] += t
            if i != j:
                info[j, i] += t
    info = 0.5 * (info + info.T)
    # correlation scaling sqrt(I_ii); parameters with no information stay exactly zero.
    # "No information" is judged unit-free: sqrt(I_jj) times the prior's spread of the
    # parameter (how many information-sds the prior spans), not sqrt(I_jj) across units.
    diag = np.sqrt(np.clip(np.diag(info), 0.0, None))
    spans = diag * _prior_spreads(model, entries)
    informative = spans > rtol * max(spans.max(), 1e-300)
    d = np.where(informative, diag, 1.0)
    scaled = info / np.outer(d, d)
    scaled[~informative, :] = 0.0
    scaled[:, ~informative] = 0.0
    lam, vec = np.linalg.eigh(scaled)
    root = np.sqrt(np.clip(lam, 0.0, None))[:, None] * vec.T
    root[:, ~informative] = 0.0
    # back to the parameters' own units, (root·D)ᵀ(root·D) = I: analyse_matrix scales the
    # columns again and maps its null directions to the units of the columns it is given
    root = root * d[None, :]
    flat_point = _flat_point(entries, values)
    report = analyse_matrix(
        root, [e[1] for e in entries], rtol=rtol, point=flat_point, kind="fisher"
    )
    report.matrix = info
    return report


def _prior_spreads(model: Any, entries: list, n: int = 256, seed: int = 0) -> np.ndarray:
    """Robust prior spread ((q95 − q05) / 3.29) of every flattened entry; 1 if undrawable."""
    import pymc as pm

    rvs = list(dict.fromkeys(rv for rv, _, _ in entries))
    try:
        draws = pm.draw(rvs, draws=n, random_seed=seed, mode="FAST_COMPILE")
    except NotImplementedError:  # improper priors (pm.Flat) cannot be drawn
        return np.ones(len(entries))
    by_rv = dict(zip(rvs, [draws] if len(rvs) == 1 else draws, strict=True))
    out = np.empty(len(entries))
    for i, (rv, _, k) in enumerate(entries):
        values = np.asarray(by_rv[rv], float).reshape(n, -1)[:, 0 if k is None else k]
        q05, q95 = np.quantile(values, [0.05, 0.95])
        spread = (q95 - q05) / 3.29
        out[i] = spread if np.isfinite(spread) and spread > 0 else 1.0
    return out


def _finite(*arrays: np.ndarray) -> bool:
    """Whether every entry of every array is finite."""
    return all(bool(np.all(np.isfinite(a))) for a in arrays)
