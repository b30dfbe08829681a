"""When no closed form explains the gap: which inputs matter (ARD), and a cross-validated check.

The closed-form search (:mod:`kohpymc.discovery.search`) always returns a most probable
explanation, even when the missing effect has no form in the candidate space (a bump
``sin(3t)·exp(-t)``, a logistic step).  This module decides, on the calibration data only,
whether that explanation is good enough, and if not, which inputs a GP discrepancy should
depend on.

**Relevance (ARD).**  A GP with a squared-exponential ARD kernel over the inputs (each
scaled to its range) is fitted to the calibration residual by type-II maximum likelihood,
with the physics parameters re-fitted jointly: the constant and the columns of the physics
Jacobian ``J`` are a linear mean with a flat prior, so the likelihood is the *restricted*
one of the residual projected onto the complement of ``[1, J]`` (a trend the physics
parameters can absorb earns the GP nothing).  An input is *relevant* when removing it
from the kernel lowers the maximised log marginal likelihood by more than half the χ²₁
quantile at ``level / d`` (a likelihood-ratio test, Bonferroni over the ``d`` inputs);
the report also gives ``range / length scale`` per input.

**Cross-validated check.**  K-fold cross-validation inside the calibration data compares
the held-out residual RMSE of three predictors, each re-fitted on the training folds: the
physics parameters alone (``J`` by least squares), the closed-form explanation
(``[J, 1, Φ_S]``: every explanation comes with the constant, so "a constant offset" alone
is ``[J, 1]``) and the GP over the relevant inputs (universal kriging with ``[1, J]``
as the mean, hyperparameters from the full-data fit).  The closed form is *rejected* when
it does not lower the held-out RMSE of the physics alone (and the GP does), when the
GP's held-out RMSE is smaller by more than the factor ``ratio``, or when its posterior
probability is below ``min_probability`` and the GP's held-out RMSE is smaller by 10 %
(with no relevant input there is nothing to fall back to).  A closed form that
is right leaves noise only, which a GP cannot predict better; one that is wrong leaves
structure that the GP predicts.  The check is deliberately lenient: a GP does not
extrapolate, so an approximate closed form (drag as ``t³/m`` to leading order) is kept.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize
from scipy.stats import chi2

__all__ = ["Relevance", "ClosedFormCheck", "ard_relevance", "check_closed_form", "kfold_rmse"]

_LOG_2PI = float(np.log(2 * np.pi))
#: an improbable closed form is rejected only when the GP's held-out RMSE is this much smaller
#: (on the benchmark, T⁴ at 5 % noise: P ≈ 0.09 and the GP 0.2-1.6 % better — noise, not a sign)
_MARGIN = 1.1


@dataclass
class Relevance:
    """Result of :func:`ard_relevance`.

    Attributes
    ----------
    relevant : list of str
        Inputs the residual depends on, most relevant first.
    log_ml_drop : dict input -> float
        Drop of the maximised (restricted) log marginal likelihood when the input is
        removed from the kernel.
    inverse_length : dict input -> float
        ``range / length scale`` of each input in the full fit (0: constant input).
    log_ml : float
        Maximised log marginal likelihood with every input.
    log_ml_noise : float
        The same without a GP (noise only).
    hyper : dict
        Fitted ``eta``, ``noise`` and ``length`` (per input, in units of its range) of the
        GP over the relevant inputs.
    cutoff : float
        The drop an input needed to count as relevant.
    """

    relevant: list[str]
    log_ml_drop: dict[str, float]
    inverse_length: dict[str, float]
    log_ml: float
    log_ml_noise: float
    hyper: dict = field(default_factory=dict)
    cutoff: float = 0.0


def _scaled(inputs: Mapping[str, np.ndarray], names: Sequence[str]) -> np.ndarray:
    cols = []
    for k in names:
        x = np.asarray(inputs[k], dtype=float)
        span = float(np.ptp(x))
        cols.append((x - x.min()) / span if span > 0 else np.zeros_like(x))
    return np.column_stack(cols) if cols else np.zeros((0, 0))


def _complement(H: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis of the complement of the column span of ``H``."""
    U, s, _ = np.linalg.svd(H, full_matrices=True)
    rank = int(np.sum(s > rtol * s.max())) if s.size else 0
    return U[:, rank:]


def _sq_dist(X: np.ndarray, Y: np.ndarray, ls: np.ndarray) -> np.ndarray:
    A, B = X / ls, Y / ls
    return np.maximum(np.sum(A**2, 1)[:, None] + np.sum(B**2, 1)[None, :] - 2 * A @ B.T, 0.0)


def _restricted_log_ml(r_t, N, X, log_eta, log_ls, noise_sd):
    """Restricted log marginal likelihood of ``Nᵀ r`` under ``η² K + σ² I``."""
    K = np.exp(2 * log_eta) * np.exp(-0.5 * _sq_dist(X, X, np.exp(log_ls)))
    C = N.T @ K @ N + (noise_sd**2 + 1e-10) * np.eye(N.shape[1])
    try:
        L = cho_factor(C, lower=True)
    except np.linalg.LinAlgError:
        return -np.inf
    alpha = cho_solve(L, r_t)
    return float(-0.5 * r_t @ alpha - np.sum(np.log(np.diag(L[0]))) - 0.5 * r_t.size * _LOG_2PI)


def _fit(r, H, X, noise_sd, starts: int = 3, seed: int = 0):
    """Type-II ML of (log η, log l, log σ) for the columns ``X``; returns (log_ml, params)."""
    N = _complement(H)
    r_t = N.T @ r
    scale = float(np.sqrt(np.mean(r_t**2))) if r_t.size else 1.0
    scale = scale if scale > 0 else 1.0
    d = X.shape[1]
    known = noise_sd is not None

    def unpack(v):
        sd = noise_sd / scale if known else np.exp(v[-1])
        return v[0], v[1 : 1 + d], sd

    def neg(v):
        log_eta, log_ls, sd = unpack(v)
        val = _restricted_log_ml(r_t / scale, N, X, log_eta, log_ls, sd)
        return -val if np.isfinite(val) else 1e30

    bounds = [(-8.0, 3.0)] + [(np.log(0.03), np.log(30.0))] * d
    bounds += [] if known else [(-9.0, 1.0)]
    rng = np.random.default_rng(seed)
    best = None
    for i in range(starts):
        v0 = [np.log(0.7)] + list(np.log(np.full(d, 0.4) if i == 0 else rng.uniform(0.1, 2, d)))
        v0 += [] if known else [np.log(0.3 if i == 0 else rng.uniform(0.05, 0.8))]
        res = minimize(neg, np.array(v0), method="L-BFGS-B", bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    log_eta, log_ls, sd = unpack(best.x)
    # back to the residual's units (the likelihood of r, not of r / scale)
    log_ml = -best.fun - r_t.size * np.log(scale)
    return float(log_ml), {
        "eta": float(np.exp(log_eta) * scale),
        "length": np.exp(log_ls),
        "noise": float(sd * scale),
    }


def _noise_only(r, H, noise_sd) -> float:
    N = _complement(H)
    r_t = N.T @ r
    m = r_t.size
    sd = float(np.sqrt(np.mean(r_t**2))) if noise_sd is None else float(noise_sd)
    sd = max(sd, 1e-300)
    return float(-0.5 * np.sum(r_t**2) / sd**2 - m * np.log(sd) - 0.5 * m * _LOG_2PI)


def _basis(jacobian: np.ndarray, n: int) -> np.ndarray:
    return np.column_stack([np.ones(n), np.asarray(jacobian, dtype=float).reshape(n, -1)])


def ard_relevance(
    inputs: Mapping[str, np.ndarray],
    residual: np.ndarray,
    jacobian: np.ndarray,
    names: Sequence[str] | None = None,
    *,
    noise_sd: float | None = None,
    level: float = 0.01,
    seed: int = 0,
) -> Relevance:
    """Which inputs the residual depends on: ARD GP fitted by type-II maximum likelihood.

    Parameters
    ----------
    inputs : mapping name -> array
        The calibration inputs.
    residual : array (n,)
        ``y - G(x; θ̂)`` on the calibration data.
    jacobian : array (n, p)
        ``∂G/∂θ`` at θ̂ (with the constant: the GP's flat-prior linear mean).
    names : sequence of str, optional
        Inputs to consider (default all of ``inputs``).
    noise_sd : float, optional
        Known noise sd; else fitted.
    level : float
        Level of the likelihood-ratio test per input (Bonferroni over the inputs).
    seed : int
        Seed of the optimiser's random starts.

    Returns
    -------
    Relevance

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> x = {"t": np.linspace(0, 4, 40), "h": rng.uniform(0, 1, 40)}
    >>> r = np.sin(3 * x["t"]) * np.exp(-x["t"]) + rng.normal(0, 0.02, 40)
    >>> ard_relevance(x, r, np.zeros((40, 0))).relevant
    ['t']
    """
    names = list(inputs) if names is None else list(names)
    r = np.asarray(residual, dtype=float).reshape(-1)
    n = r.size
    H = _basis(jacobian, n)
    varying = [k for k in names if np.ptp(np.asarray(inputs[k], dtype=float)) > 0]
    X = _scaled(inputs, varying)
    log_ml_noise = _noise_only(r, H, noise_sd)
    drop = {k: 0.0 for k in names}
    inverse = {k: 0.0 for k in names}
    if not varying:
        return Relevance([], drop, inverse, log_ml_noise, log_ml_noise)
    full, params = _fit(r, H, X, noise_sd, seed=seed)
    for j, k in enumerate(varying):
        inverse[k] = float(1.0 / params["length"][j])
        rest = [i for i in range(len(varying)) if i != j]
        without = _fit(r, H, X[:, rest], noise_sd, seed=seed)[0] if rest else log_ml_noise
        drop[k] = float(full - max(without, log_ml_noise))
    cutoff = 0.5 * float(chi2.isf(level / len(varying), 1))
    relevant = sorted((k for k in varying if drop[k] > cutoff), key=lambda k: -drop[k])
    hyper: dict = {}
    if relevant:
        cols = [varying.index(k) for k in relevant]
        _, fitted = _fit(r, H, X[:, cols], noise_sd, seed=seed)
        hyper = {**fitted, "length": dict(zip(relevant, fitted["length"].tolist(), strict=True))}
    return Relevance(relevant, drop, inverse, full, log_ml_noise, hyper, cutoff)


def _kriging(r_tr, H_tr, H_te, X_tr, X_te, hyper) -> np.ndarray:
    """Universal-kriging mean at the test rows (flat prior on the linear-mean coefficients)."""
    ls = np.array(list(hyper["length"].values()))
    eta2, s2 = hyper["eta"] ** 2, hyper["noise"] ** 2
    C = eta2 * np.exp(-0.5 * _sq_dist(X_tr, X_tr, ls)) + (s2 + 1e-10) * np.eye(len(r_tr))
    Ks = eta2 * np.exp(-0.5 * _sq_dist(X_te, X_tr, ls))
    L = cho_factor(C, lower=True)
    Ci_H, Ci_r = cho_solve(L, H_tr), cho_solve(L, r_tr)
    beta = np.linalg.lstsq(H_tr.T @ Ci_H, H_tr.T @ Ci_r, rcond=None)[0]
    return H_te @ beta + Ks @ cho_solve(L, r_tr - H_tr @ beta)


def kfold_rmse(
    residual: np.ndarray,
    columns: np.ndarray,
    *,
    folds: int = 5,
    seed: int = 0,
) -> float:
    """Held-out RMSE of the least-squares fit of ``residual`` on ``columns``, K-fold.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0, 1, 30)
    >>> r = 2 * x + np.random.default_rng(1).normal(0, 0.1, 30)
    >>> round(kfold_rmse(r, np.c_[np.ones(30), x]), 1), kfold_rmse(r, np.c_[np.ones(30)]) > 0.5
    (0.1, True)
    """
    r = np.asarray(residual, dtype=float).reshape(-1)
    A = np.asarray(columns, dtype=float).reshape(r.size, -1)
    err = np.empty(r.size)
    for test in _folds(r.size, folds, seed):
        train = np.setdiff1d(np.arange(r.size), test)
        beta = np.linalg.lstsq(A[train], r[train], rcond=None)[0]
        err[test] = r[test] - A[test] @ beta
    return float(np.sqrt(np.mean(err**2)))


def _folds(n: int, folds: int, seed: int) -> list[np.ndarray]:
    order = np.random.default_rng(seed).permutation(n)
    return [np.sort(order[i::folds]) for i in range(folds)]


@dataclass
class ClosedFormCheck:
    """Result of :func:`check_closed_form`.

    Attributes
    ----------
    rejected : bool
        Whether the closed-form explanation is rejected (fall back to a GP).
    reason : str
        Why (or why not), in words.
    cv_rmse : dict
        Held-out residual RMSE by K-fold cross-validation inside the calibration data:
        ``"physics"`` (θ re-fitted only), ``"closed_form"``, ``"gp"`` (None without a
        relevant input).
    folds : int
        Number of folds.
    relevance : Relevance
        The ARD relevance of the inputs.
    """

    rejected: bool
    reason: str
    cv_rmse: dict
    folds: int
    relevance: Relevance

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        rel = self.relevance
        return {
            "closed_form_rejected": self.rejected,
            "reason": self.reason,
            "cv_folds": self.folds,
            "cv_rmse": self.cv_rmse,
            "cv_improves": self.cv_rmse["closed_form"] < self.cv_rmse["physics"],
            "relevant_inputs": list(rel.relevant),
            "log_ml_drop": rel.log_ml_drop,
            "range_over_length_scale": rel.inverse_length,
            "relevance_cutoff": rel.cutoff,
        }


def check_closed_form(
    inputs: Mapping[str, np.ndarray],
    residual: np.ndarray,
    jacobian: np.ndarray,
    closed_form: np.ndarray,
    probability: float,
    *,
    names: Sequence[str] | None = None,
    noise_sd: float | None = None,
    folds: int = 5,
    min_probability: float = 0.1,
    ratio: float = 1.3,
    level: float = 0.01,
    seed: int = 0,
) -> ClosedFormCheck:
    """Whether the closed-form explanation is good enough, or a GP should take over.

    Everything here uses the calibration data only (see the module docstring).

    Parameters
    ----------
    inputs : mapping name -> array
        Calibration inputs.
    residual : array (n,)
        Calibration residual of the model as given.
    jacobian : array (n, p)
        ``∂G/∂θ`` at θ̂.
    closed_form : array (n, k)
        Columns of the terms of the most probable explanation (shaped terms at their
        fitted scale; the constant is added here).
    probability : float
        Posterior probability of that explanation.
    names : sequence of str, optional
        Inputs a GP may depend on (default all).
    noise_sd : float, optional
        Known noise sd.
    folds : int
        K of the K-fold cross-validation.
    min_probability : float
        A closed form less probable than this is rejected when a GP predicts held-out
        rows 10 % better.
    ratio : float
        The closed form is rejected when its held-out RMSE exceeds the GP's by this
        factor.
    level : float
        Level of the relevance test.
    seed : int
        Seed of the folds and the optimiser.

    Returns
    -------
    ClosedFormCheck

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(2)
    >>> t = np.linspace(0, 4, 40)
    >>> r = np.sin(3 * t) * np.exp(-t) + rng.normal(0, 0.02, 40)
    >>> chk = check_closed_form({"t": t}, r, np.zeros((40, 0)), np.c_[np.exp(-t)], 0.9)
    >>> chk.rejected, chk.relevance.relevant
    (True, ['t'])
    """
    r = np.asarray(residual, dtype=float).reshape(-1)
    n = r.size
    H = _basis(jacobian, n)
    Phi = np.asarray(closed_form, dtype=float).reshape(n, -1)
    rel = ard_relevance(inputs, r, jacobian, names, noise_sd=noise_sd, level=level, seed=seed)
    # the physics parameters alone: J without the constant (which every explanation adds)
    cv_physics = kfold_rmse(r, H[:, 1:], folds=folds, seed=seed)
    cv_closed = kfold_rmse(r, np.column_stack([H, Phi]), folds=folds, seed=seed)
    cv: dict[str, float | None] = {"physics": cv_physics, "closed_form": cv_closed, "gp": None}
    if rel.relevant:
        cv["gp"] = _gp_cv_rmse(inputs, r, H, rel, folds, seed)
    reason = _reason(cv, probability, min_probability, ratio, rel)
    if reason is not None:
        return ClosedFormCheck(True, reason, cv, folds, rel)
    return ClosedFormCheck(False, _kept_reason(cv_closed, cv_physics, cv["gp"]), cv, folds, rel)


def _gp_cv_rmse(inputs, r: np.ndarray, H: np.ndarray, rel, folds: int, seed: int) -> float:
    """K-fold held-out RMSE of the GP on the relevant inputs (kriging with basis ``H``)."""
    n = r.size
    X = _scaled(inputs, rel.relevant)
    err = np.empty(n)
    for test in _folds(n, folds, seed):
        train = np.setdiff1d(np.arange(n), test)
        err[test] = r[test] - _kriging(r[train], H[train], H[test], X[train], X[test], rel.hyper)
    return float(np.sqrt(np.mean(err**2)))


def _kept_reason(cv_closed: float, cv_physics: float, cv_gp: float | None) -> str:
    """Why the closed form is kept (no GP beats it on held-out rows)."""
    if cv_closed >= cv_physics:
        return "the closed form does not lower the held-out calibration residual, nor does a GP"
    if cv_gp is None:
        return "the closed form lowers the held-out calibration residual; no input left for a GP"
    return "the closed form predicts held-out calibration rows about as well as a GP"


def _reason(cv, probability, min_probability, ratio, rel) -> str | None:
    gp = cv["gp"]
    if gp is None:  # no input is relevant: nothing for a GP to take over
        return None
    if cv["closed_form"] >= cv["physics"] and gp < cv["physics"]:
        return "the closed form does not lower the held-out calibration residual; a GP does"
    if cv["closed_form"] > ratio * gp:
        return (
            f"a GP over {', '.join(rel.relevant)} predicts held-out calibration rows better "
            f"(RMSE {gp:.3g} vs {cv['closed_form']:.3g} for the closed form)"
        )
    if probability < min_probability and cv["closed_form"] > _MARGIN * gp:
        return (
            f"the most probable closed form has posterior probability {probability:.2g} "
            f"and a GP predicts held-out calibration rows better (RMSE {gp:.3g} vs "
            f"{cv['closed_form']:.3g})"
        )
    return None
