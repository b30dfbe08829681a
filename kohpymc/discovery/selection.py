"""The term selection: posterior over explanations and a calibrated false-alarm rate.

The decision "something is missing" is taken on the posterior probability of "nothing
missing", ``P₀``, calibrated by simulation: under the linearised null model the
residual is ``(I - P_J) ε`` with ``ε ~ N(0, σ² I)``, and ``P₀`` is invariant to σ when
σ is integrated out (and depends only on ``ε/σ`` when σ is known), so its null
distribution follows from ``null_draws`` standard-normal residuals pushed through the
same search.  The p-value is ``(1 + #{P₀_null ≤ P₀}) / (1 + null_draws)`` and a missing
effect is declared when it is at most ``false_alarm``: with ``null_draws = 299`` the
rate is exactly 0.01 (0.05) at ``false_alarm = 0.01`` (0.05) for the linearised model.
The simulation stops early once ten null residuals beat the observed one (Besag and
Clifford's sequential p-value, which is just as valid), so a data set with nothing
missing costs a few dozen simulated residuals, not ``null_draws``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from kohpymc.candidates import CandidateTerm
from kohpymc.discovery.evidence import TermSelection
from kohpymc.discovery.search import Design, build_design, explain, probability_none

__all__ = ["null_probabilities", "select_terms"]


def _posterior(log_post: dict) -> dict:
    keys = list(log_post)
    lp = np.array([log_post[k] for k in keys])
    post = np.exp(lp - lp.max())
    post /= post.sum()
    return dict(zip(keys, post, strict=True))


def null_probabilities(
    design: Design,
    *,
    noise_sd: float | None,
    draws: int = 299,
    random_seed: int = 0,
    **search,
) -> np.ndarray:
    """``P(nothing missing)`` on ``draws`` residuals simulated under the null model.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0, 1, 20)
    >>> d = build_design(np.c_[x], np.c_[x**2, x**3], ["x^2", "x^3"])
    >>> p0 = null_probabilities(d, noise_sd=None, draws=50, max_terms=1)
    >>> p0.shape, bool(np.median(p0) > 0.5)
    ((50,), True)
    """
    rng = np.random.default_rng(random_seed)
    scale = 1.0 if noise_sd is None else float(noise_sd)
    out = np.empty(draws)
    for i in range(draws):
        z = scale * rng.standard_normal(design.n)
        out[i] = probability_none(design, z, noise_sd=noise_sd, **search)
    return out


def _sequential_p_value(design, observed, *, noise_sd, draws, seed, stop=10, **search):
    """Monte Carlo p-value of ``P(nothing missing)``, stopping early (Besag & Clifford 1991).

    Null residuals are drawn until ``stop`` of them have a probability of "nothing
    missing" at most the observed one (then ``p = stop / drawn``) or ``draws`` were
    drawn (then ``p = (1 + exceedances) / (1 + draws)``); both are valid p-values.
    """
    rng = np.random.default_rng(seed)
    scale = 1.0 if noise_sd is None else float(noise_sd)
    hits = 0
    for i in range(draws):
        z = scale * rng.standard_normal(design.n)
        hits += probability_none(design, z, noise_sd=noise_sd, **search) <= observed
        if hits >= stop:
            return float(stop / (i + 1))
    return float((1 + hits) / (1 + draws))


def _check(r, J, candidates, names, max_terms, false_alarm):
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise ValueError("residual and Jacobian must be finite")
    if isinstance(candidates, np.ndarray):
        if candidates.shape[1] == 0:
            raise ValueError("no candidate terms to select from")
        if names is None or candidates.shape[1] != len(names):
            n_names = None if names is None else len(names)
            raise ValueError(f"{candidates.shape[1]} candidate columns but {n_names} names")
        if not np.all(np.isfinite(candidates)):
            raise ValueError("candidate columns must be finite")
    elif len(candidates) == 0:
        raise ValueError("no candidate terms to select from")
    if max_terms < 1:
        raise ValueError("max_terms must be at least 1")
    if not 0 < false_alarm < 1:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm!r}")
    if r.size <= J.shape[1] + 2:
        raise ValueError(
            f"too few data points ({r.size}) for {J.shape[1]} parameters and any candidate term"
        )


def select_terms(
    residual: np.ndarray,
    jacobian: np.ndarray,
    candidates: np.ndarray | Sequence[CandidateTerm],
    names: Sequence[str] | None = None,
    *,
    inputs: dict | None = None,
    noise_sd: float | None,
    max_terms: int = 3,
    false_alarm: float = 0.01,
    null_draws: int = 299,
    random_seed: int = 0,
    screen: int = 30,
    partners: int = 5,
    g: float | None = None,
    rtol: float = 1e-7,
    borrowed: tuple[np.ndarray, np.ndarray] | None = None,
) -> TermSelection:
    """Posterior over explanations of the residual of a calibrated model.

    Parameters
    ----------
    residual : array (n,)
        ``y - G(x; θ̂)``.
    jacobian : array (n, p)
        ``∂G/∂θ`` at θ̂ (the physics parameters are re-fitted jointly with the terms).
    candidates : array (n, k) or sequence of CandidateTerm
        Candidate columns with ``names``, or terms with ``inputs``.
    names : sequence of str, optional
        Names of the candidate columns.
    inputs : mapping, optional
        The data's inputs (for terms).
    noise_sd : float or None
        Known measurement-noise sd; None integrates σ out.
    max_terms : int
        Largest number of terms in one explanation (besides the constant).
    false_alarm : float
        Rate of false alarms the decision is calibrated to (by simulation).
    null_draws : int
        Simulated null residuals; 0 skips the calibration (``p_value`` None).
    random_seed : int
        Seed of the null simulation.
    screen, partners : int
        Search breadth (see :mod:`kohpymc.discovery.search`).
    g : float, optional
        The g-prior's g (default n).
    rtol : float
        Tolerance of the identifiability (span) check.
    borrowed : (A, b), optional
        θ borrowed from other data (other outputs): rows ``b = A Δθ + ε`` appended to
        the residual, in its units and with its noise, that carry what those data say
        about Δθ (``AᵀA`` their information, ``AᵀA Δθ̂ = Aᵀb`` their estimate).  The
        terms are zero on these rows; Δθ is re-fitted from the residual *and* them.
        See :func:`kohpymc.multi_output.discovery.borrowed_rows`.

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
    >>> sel = select_terms(r, J, Phi, ["x", "x^2", "1"], noise_sd=None, null_draws=99)
    >>> sel.best, sorted(sel.rejected), sel.significant
    (('x^2',), ['1'], True)
    """
    r = np.asarray(residual, dtype=float).reshape(-1)
    J = np.asarray(jacobian, dtype=float).reshape(r.size, -1)
    _check(r, J, candidates, names, max_terms, false_alarm)
    A = None
    if borrowed is not None:
        A = np.asarray(borrowed[0], dtype=float).reshape(-1, J.shape[1])
        b = np.asarray(borrowed[1], dtype=float).reshape(A.shape[0])
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
            raise ValueError("borrowed rows must be finite")
        r = np.r_[r, b]
    design = _usable_design(J, candidates, names, inputs, rtol, A)
    search: dict[str, Any] = dict(max_terms=max_terms, screen=screen, partners=partners, g=g)
    log_post, log_bf, fitted = explain(design, r, noise_sd=noise_sd, **search)
    post = _posterior(log_post)
    p_value = None
    if null_draws > 0:
        p_value = _sequential_p_value(
            design, post[()], noise_sd=noise_sd, draws=null_draws, seed=random_seed, **search
        )
    return _selection(design, post, log_bf, fitted, p_value, false_alarm)


def _usable_design(J, candidates, names, inputs, rtol: float, borrowed=None):
    """The candidate design (:func:`build_design`); an error when every term was rejected."""
    design = build_design(J, candidates, names, inputs=inputs, rtol=rtol, borrowed=borrowed)
    if design.size == 0:
        raise ValueError(
            "every candidate term was rejected: "
            + "; ".join(f"{k}: {v}" for k, v in design.rejected.items())
        )
    return design


def _selection(design, post, log_bf, fitted, p_value, false_alarm: float) -> TermSelection:
    """The selection: explanations ranked by posterior probability, inclusion of each term."""
    ranked = sorted(post.items(), key=lambda kv: -kv[1])
    inclusion: dict[str, float] = {}
    for subset, p in ranked:
        for name in subset:
            inclusion[name] = inclusion.get(name, 0.0) + float(p)
    terms = {**design.terms, **fitted}
    return TermSelection(
        best=ranked[0][0],
        probability_none=float(post[()]),
        inclusion=inclusion,
        subsets=[(s, float(p)) for s, p in ranked],
        rejected=dict(design.rejected),
        merged=dict(design.merged),
        p_value=p_value,
        false_alarm=false_alarm,
        terms={name: terms.get(name) for s, _ in ranked[:50] for name in s if name != "1"},
        log_bayes_factors={(): 0.0, **{s: log_bf[s] for s, _ in ranked[:50]}},
        constant=design.u is not None,
    )
