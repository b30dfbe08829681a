"""The term comparison: Bayesian evidence of candidate subsets (see :mod:`kohpymc.discovery`)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from kohpymc.identifiability import analyse_matrix

__all__ = ["TermSelection", "select_terms"]


@dataclass
class TermSelection:
    """Result of :func:`select_terms`.

    Attributes
    ----------
    best : tuple of str
        Names of the most probable subset (empty: nothing missing).
    probability_none : float
        Posterior probability that no candidate term is needed.
    inclusion : dict name -> float
        Posterior inclusion probability of each admissible candidate.
    subsets : list of (tuple of str, float)
        Subsets with their posterior probabilities, most probable first.
    rejected : dict name -> str
        Candidates rejected before the comparison, with the reason.
    """

    best: tuple[str, ...]
    probability_none: float
    inclusion: dict[str, float]
    subsets: list[tuple[tuple[str, ...], float]]
    rejected: dict[str, str] = field(default_factory=dict)


def _log_evidence(r: np.ndarray, base: np.ndarray, Phi: np.ndarray, coef_sd: float, sd):
    """Log N(r; 0, base + σ² I + s_c² Φ Φᵀ); ``sd`` a float or None (maximised)."""
    extra = base + (coef_sd**2) * (Phi @ Phi.T) if Phi.size else base
    n = r.size

    def logpdf(log_sd: float) -> float:
        cov = extra + np.exp(2 * log_sd) * np.eye(n)
        chol = np.linalg.cholesky(cov)
        z = np.linalg.solve(chol, r)
        return float(-0.5 * z @ z - np.sum(np.log(np.diag(chol))) - 0.5 * n * np.log(2 * np.pi))

    if sd is not None:
        return logpdf(np.log(sd))
    scale = max(float(np.std(r)), 1e-12)
    res = minimize_scalar(
        lambda s: -logpdf(s), bounds=(np.log(scale) - 12, np.log(scale) + 2), method="bounded"
    )
    return -float(res.fun)


def select_terms(
    residual: np.ndarray,
    jacobian: np.ndarray,
    candidates: np.ndarray,
    names: Sequence[str],
    *,
    noise_sd: float | None,
    parameter_sd: Sequence[float],
    coefficient_sd: float | None = None,
    max_terms: int = 2,
    rtol: float = 1e-7,
) -> TermSelection:
    """Posterior over small subsets of candidate terms for the residual of a calibrated model.

    Parameters
    ----------
    residual : array (n,)
        ``y - G(x; θ̂)``.
    jacobian : array (n, p)
        ``∂G/∂θ`` at θ̂.
    candidates : array (n, k)
        Candidate columns (see :func:`kohpymc.candidates.design_matrix`).
    names : sequence of str
        Names of the candidate columns.
    noise_sd : float or None
        Measurement-noise sd; None estimates it per subset (type-II ML).
    parameter_sd : sequence of float
        Prior sd of each physics parameter around θ̂ (e.g. its prior's sd).
    coefficient_sd : float, optional
        Prior sd of each coefficient of a unit-sd candidate column; default ``2 · sd(r)``
        (at least ``noise_sd``).
    max_terms : int
        Largest subset size considered.
    rtol : float
        Relative singular-value tolerance of the identifiability check.

    Returns
    -------
    TermSelection

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> x = np.linspace(0, 1, 40)
    >>> J = np.c_[np.ones_like(x)]                      # the physics can shift the level
    >>> Phi = np.c_[x, x**2, np.ones_like(x)]           # the last one it can mimic
    >>> r = 0.5 + 2.0 * x**2 + rng.normal(0, 0.05, x.size)
    >>> sel = select_terms(r, J, Phi, ["x", "x^2", "1"], noise_sd=0.05, parameter_sd=[10.0])
    >>> sel.best, sorted(sel.rejected)
    (('x^2',), ['1'])
    """
    r = np.asarray(residual, dtype=float).reshape(-1)
    J = np.asarray(jacobian, dtype=float).reshape(r.size, -1)
    C = np.asarray(candidates, dtype=float).reshape(r.size, -1)
    names = [str(n) for n in names]
    if C.shape[1] != len(names):
        raise ValueError(f"{C.shape[1]} candidate columns but {len(names)} names")
    if C.shape[1] == 0:
        raise ValueError("no candidate terms to select from")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J)) and np.all(np.isfinite(C))):
        raise ValueError("residual, Jacobian and candidate columns must be finite")
    if max_terms < 1:
        raise ValueError("max_terms must be at least 1")
    theta_sd = np.asarray(parameter_sd, dtype=float).reshape(-1)
    if theta_sd.size != J.shape[1]:
        raise ValueError(f"{theta_sd.size} parameter sds for {J.shape[1]} Jacobian columns")
    if r.size <= J.shape[1] + 1:
        raise ValueError(
            f"too few data points ({r.size}) for {J.shape[1]} parameters and any candidate term"
        )

    rejected, admissible = _screen(J, C, names, rtol)
    if not admissible:
        raise ValueError(
            "every candidate term was rejected: "
            + "; ".join(f"{k}: {v}" for k, v in rejected.items())
        )
    scale = np.std(C[:, admissible], axis=0)
    scale = np.where(scale > 0, scale, np.abs(C[:, admissible]).max(axis=0))
    Phi = C[:, admissible] / scale
    adm_names = [names[j] for j in admissible]
    base = (J * theta_sd**2) @ J.T
    s_c = coefficient_sd or max(2.0 * float(np.std(r)), noise_sd or 0.0)
    sizes = range(0, min(max_terms, len(adm_names)) + 1)
    log_post: list[float] = []
    subsets: list[tuple[int, ...]] = []
    for size in sizes:
        combos = list(itertools.combinations(range(len(adm_names)), size))
        prior = np.log(0.5) if size == 0 else np.log(0.5 / (len(sizes) - 1) / len(combos))
        for combo in combos:
            ev = _log_evidence(r, base, Phi[:, list(combo)], s_c, noise_sd)
            subsets.append(combo)
            log_post.append(ev + prior)
    lp = np.array(log_post)
    post = np.exp(lp - lp.max())
    post /= post.sum()
    order = np.argsort(-post, kind="stable")
    inclusion = {
        name: float(sum(p for s, p in zip(subsets, post, strict=True) if i in s))
        for i, name in enumerate(adm_names)
    }
    ranked = [(tuple(adm_names[i] for i in subsets[o]), float(post[o])) for o in order]
    return TermSelection(
        best=ranked[0][0],
        probability_none=float(post[0]),
        inclusion=inclusion,
        subsets=ranked,
        rejected=rejected,
    )


def _screen(J: np.ndarray, C: np.ndarray, names: list[str], rtol: float):
    """Candidates rejected before the comparison (with the reason) and the admissible ones."""
    rejected: dict[str, str] = {}
    admissible: list[int] = []
    for j, name in enumerate(names):
        col = C[:, j]
        if np.ptp(col) == 0 and np.all(col == 0):
            rejected[name] = "identically zero on the data"
            continue
        labels = [f"theta{i}" for i in range(J.shape[1])] + [name]
        report = analyse_matrix(np.column_stack([J, col]), labels, rtol=rtol)
        if report.rank < J.shape[1] + 1:
            rejected[name] = (
                "not identifiable together with the physics parameters (its column lies in "
                "the span of dG/dtheta)"
            )
            continue
        admissible.append(j)
    return rejected, admissible
