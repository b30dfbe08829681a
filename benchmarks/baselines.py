"""Reference baselines of ``make bench``: numpy log posteriors and random-walk Metropolis.

For each beam formulation M0–M5 (:func:`beam_formulations`) :func:`numpy_log_posterior`
writes the log posterior of ``build_model(beam.physics_model(), data, formulation)`` in
plain numpy/scipy (no PyTensor), on the unconstrained coordinates PyMC samples:

* ``E_interval__`` — ``E = 50 + 250 · expit(v)`` (PyMC's interval transform of the
  Uniform(50, 300) prior), log-Jacobian ``log expit(v) + log expit(-v)``;
* ``*_log__`` — positive scales on the log scale (HalfNormal, InverseGamma priors),
  log-Jacobian ``v``;
* ``delta_logvar`` — M3's log-variance coefficients (normal priors, no transform);
* ``*_white`` — the whitened linear-mean coefficients, independent N(0, 1) because the
  coefficients are integrated out of the likelihood (``marginalize=True``).

All normalising constants are kept, so the value equals ``model.compile_logp()`` at the
same point (``tests/test_bench_baselines.py`` checks it: ~1e-12 for M0–M3; M4/M5 differ
by a constant 2.2e-8 because PyMC evaluates ``gammaln(4)`` of the InverseGamma length-scale
prior in float32, its α = 4.0 being a float32 constant).  Everything that does
not depend on the parameters (the physics shape ``a(x) = G(x; E) · E``, data sums, the
basis, squared distances) is precomputed: a call costs a few scalar operations (M0–M2), a
10-column weighted sum (M3, Woodbury identity for the 2-term basis) or one 20 × 20
Cholesky factorisation (M4, M5, via LAPACK ``dpotrf``/``dtrtrs``).

:func:`random_walk_metropolis` is the paper's sampler: a Gaussian random walk whose
covariance is adapted during tuning (empirical covariance × a scalar step tuned to the
optimal acceptance) and fixed afterwards.  :func:`run_baseline` runs it for one
formulation and returns the benchmark row.  The whitened coefficients are exactly
independent standard normals *a posteriori*, so by default (``white=False``) the random
walk explores only E and the discrepancy hyperparameters (the most favourable set-up for
the baseline); ``white=True`` samples PyMC's full coordinate set.

Run ``python benchmarks/baselines.py`` for the table of all formulations.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import arviz as az
import numpy as np
import pandas as pd
from scipy.linalg.lapack import dpotrf, dtrtrs
from scipy.optimize import minimize
from scipy.special import expit, gammaln

from kohpymc.data import CalibrationData
from kohpymc.examples import beam

__all__ = [
    "DATA_PATH",
    "LABELS",
    "NumpyPosterior",
    "RWMResult",
    "beam_formulations",
    "find_starts",
    "load_beam_data",
    "numpy_log_posterior",
    "random_walk_metropolis",
    "run_baseline",
    "summarize_E",
]

DATA_PATH = Path(beam.__file__).parent / "data" / "beam_calibration.csv"
LABELS = ("M0", "M1", "M2", "M3", "M4", "M5")
#: jitter ``pm.gp.Marginal.marginal_likelihood`` adds to the diagonal (PyMC's default)
GP_JITTER = 1e-6
_LOG2PI = math.log(2.0 * math.pi)


def load_beam_data(path: str | Path = DATA_PATH) -> CalibrationData:
    """The beam calibration data (20 rows at P = 2.5) with known noise sd ``sqrt(0.1)``.

    Parameters
    ----------
    path : str or Path
        CSV with columns ``x``, ``P``, ``u``.

    Returns
    -------
    CalibrationData
    """
    return CalibrationData.from_csv(
        path, inputs=["x", "P"], output="u", noise_sd=math.sqrt(beam.NOISE_VAR)
    )


def beam_formulations() -> dict[str, Any]:
    """M0–M4 of :func:`kohpymc.examples.beam.formulations` plus M5 (non-stationary GP on x).

    Returns
    -------
    dict
        Label -> discrepancy formulation.
    """
    from kohpymc.discrepancy import NonStationaryGP

    forms = beam.formulations()
    forms["M5"] = NonStationaryGP(["x"], time="x", mean=["x"])
    return forms


# --------------------------------------------------------------------------- log posterior
@dataclass(frozen=True)
class _Block:
    value: str  # PyMC value-variable name
    size: int
    scalar: bool  # PyMC shape () rather than (size,)
    kind: str  # "interval", "log", "identity" or "white"
    name: str  # constrained variable name


@dataclass
class NumpyPosterior:
    """A numpy log posterior on PyMC's unconstrained coordinates.

    Attributes
    ----------
    label : str
        Formulation label ``"M0"`` ... ``"M5"``.
    logp : callable
        ``logp(vec) -> float`` for a 1-D vector in the order of :attr:`names`.
    names : tuple of str
        Coordinate names, e.g. ``("E_interval__", "delta_logvar[0]", ...)``.
    blocks : tuple
        Value variables (PyMC names, sizes, transforms) making up the vector.
    init : numpy.ndarray
        A starting point for optimisation (prior centre / PyMC's initial point).
    bounds : tuple of float
        The Uniform prior bounds of E.
    dims : dict
        ArviZ dims of the vector-valued constrained variables.
    """

    label: str
    logp: Callable[[np.ndarray], float]
    names: tuple[str, ...]
    blocks: tuple[_Block, ...]
    init: np.ndarray
    bounds: tuple[float, float] = (50.0, 300.0)
    dims: dict[str, list[str]] = field(default_factory=dict)

    @property
    def ndim(self) -> int:
        """Number of coordinates."""
        return len(self.names)

    def _slices(self):
        start = 0
        for block in self.blocks:
            yield block, slice(start, start + block.size)
            start += block.size

    def to_constrained(self, vec: np.ndarray) -> dict[str, np.ndarray]:
        """Constrained named variables from vectors of shape ``(..., ndim)``.

        Parameters
        ----------
        vec : numpy.ndarray
            Unconstrained coordinates, last axis in the order of :attr:`names`.

        Returns
        -------
        dict
            ``E`` and the discrepancy parameters (``delta_sd``, ``delta_logvar``,
            ``delta_ls``, ``delta_eta``, ``delta_w1``, ``delta_w2``, ``*_white``).
        """
        vec = np.asarray(vec, dtype=float)
        lo, hi = self.bounds
        out = {}
        for block, sl in self._slices():
            v = vec[..., sl]
            if block.kind == "interval":
                v = lo + (hi - lo) * expit(v)
            elif block.kind == "log":
                v = np.exp(v)
            out[block.name] = v[..., 0] if block.scalar else v
        return out

    def to_point(self, vec: np.ndarray) -> dict[str, np.ndarray]:
        """The PyMC value-variable dict (e.g. for ``model.compile_logp()``) of one vector.

        Parameters
        ----------
        vec : numpy.ndarray
            1-D unconstrained coordinates.

        Returns
        -------
        dict
            PyMC value-variable name -> array of the variable's shape.
        """
        vec = np.asarray(vec, dtype=float)
        return {
            b.value: (np.asarray(vec[sl][0]) if b.scalar else vec[sl].copy())
            for b, sl in self._slices()
        }


def _halfnormal_log(sigma: float) -> Callable[[float], float]:
    """log HalfNormal(σ) density of ``exp(v)`` plus the log-Jacobian ``v``."""
    c = 0.5 * math.log(2.0 / math.pi) - math.log(sigma)
    k = 0.5 / sigma**2
    return lambda v: c - k * math.exp(2.0 * v) + v


def _invgamma_log(alpha: float, beta: float) -> Callable[[float], float]:
    """log InverseGamma(α, β) density of ``exp(v)`` plus the log-Jacobian ``v``."""
    c = alpha * math.log(beta) - float(gammaln(alpha))
    return lambda v: c - alpha * v - beta * math.exp(-v)


def numpy_log_posterior(
    label: str, data: CalibrationData | None = None, *, white: bool = True
) -> NumpyPosterior:
    """The log posterior of one beam formulation in numpy, on PyMC's coordinates.

    Reimplements ``kohpymc.model.build_model(beam.physics_model(), data, form)`` for
    ``form = beam_formulations()[label]`` with its default priors: E ~ Uniform(50, 300);
    mean coefficients on the basis ``[1, z]`` (``z`` = standardised x; intercept only for
    M1/M2) with N(0, (2 sd(y))²) priors integrated out; M2 ``delta_sd`` ~
    HalfNormal(sd(y)); M3 ``delta_logvar`` ~ N([2 log(0.1 sd(y)), 0], [2.5, 1]) with
    ``σ_δ²(x) = exp(c0 + c1 z)``; M4/M5 ``delta_eta`` ~ HalfNormal(sd(y)), ``delta_ls`` ~
    InverseGamma(4, 2 range(x)), SE kernel on raw x, jitter 1e-6; M5 ``delta_w1`` ~
    HalfNormal(sd(y)²), ``delta_w2`` ~ HalfNormal(5 / range(x)) and the kernel term
    ``w1 exp(-w2 x) 1[x = x']``.

    Parameters
    ----------
    label : str
        ``"M0"`` ... ``"M5"``.
    data : CalibrationData, optional
        Inputs ``x``, ``P``, output and known noise sd; default :func:`load_beam_data`.
    white : bool
        Include the whitened coefficient coordinates (``*_white``, independent N(0, 1)
        a posteriori) so the vector matches PyMC's value variables exactly; ``False``
        drops them and their (separable) density.

    Returns
    -------
    NumpyPosterior
        ``logp``, coordinate ``names``, ``to_constrained`` and ``to_point``.

    Examples
    --------
    >>> post = numpy_log_posterior("M2")
    >>> post.names
    ('E_interval__', 'delta_sd_log__', 'delta_mean_white[0]')
    """
    if label not in LABELS:
        raise ValueError(f"unknown formulation {label!r}; expected one of {LABELS}")
    data = load_beam_data() if data is None else data
    if data.noise_sd is None:
        raise ValueError("the baselines need a known noise sd")
    prior = beam.physics_model().parameters["E"].args
    lo, hi = float(prior["lower"]), float(prior["upper"])
    x = np.asarray(data.inputs["x"], dtype=float)
    y = np.asarray(data.y, dtype=float)
    a = beam.euler_bernoulli({"x": x, "P": data.inputs["P"]}, {"E": 1.0})  # G = a / E
    n = y.size
    s2 = float(data.noise_sd) ** 2
    y_scale = float(np.std(y)) or max(float(np.max(np.abs(y))), 1.0)
    z = (x - x.mean()) / (float(np.std(x)) or max(abs(float(x.mean())), 1.0))
    span = float(np.ptp(x)) or max(abs(float(x.mean())), 1.0)
    coef_var = (2.0 * y_scale) ** 2  # prior variance of each mean coefficient
    Sy, Sa, Syy, Sya, Saa = y.sum(), a.sum(), y @ y, y @ a, a @ a
    c_lik = -0.5 * n * _LOG2PI

    def e_terms(v: float) -> tuple[float, float]:
        """1/E and log prior + log-Jacobian of the interval transform."""
        e = lo + (hi - lo) * 0.5 * (1.0 + math.tanh(0.5 * v))
        av = abs(v)
        return 1.0 / e, -av - 2.0 * math.log1p(math.exp(-av))

    def rank_one(u: float, d: float) -> float:
        """log N(y; a u, d I + coef_var 1 1ᵀ) with sums precomputed."""
        rr = Syy - 2.0 * u * Sya + u * u * Saa
        sr = Sy - u * Sa
        den = d + n * coef_var
        return c_lik - 0.5 * (
            (n - 1) * math.log(d) + math.log(den) + (rr - coef_var * sr * sr / den) / d
        )

    E_block = _Block("E_interval__", 1, True, "interval", "E")
    n_white = 0
    white_name = "delta_mean_white"
    dims: dict[str, list[str]] = {}
    if label == "M0":
        blocks: list[_Block] = [E_block]
        init = [0.0]

        def core(vec: np.ndarray) -> float:
            u, lp = e_terms(vec[0])
            return (
                lp + c_lik - 0.5 * n * math.log(s2) - 0.5 * (Syy - 2 * u * Sya + u * u * Saa) / s2
            )

    elif label == "M1":
        blocks, init, n_white, white_name = [E_block], [0.0], 1, "delta_white"

        def core(vec: np.ndarray) -> float:
            u, lp = e_terms(vec[0])
            return lp + rank_one(u, s2)

    elif label == "M2":
        blocks = [E_block, _Block("delta_sd_log__", 1, True, "log", "delta_sd")]
        init, n_white = [0.0, math.log(y_scale)], 1
        sd_prior = _halfnormal_log(y_scale)

        def core(vec: np.ndarray) -> float:
            u, lp = e_terms(vec[0])
            w = vec[1]
            return lp + sd_prior(w) + rank_one(u, s2 + math.exp(2.0 * w))

    elif label == "M3":
        dims["delta_logvar"] = ["delta_logvar_term"]
        blocks = [E_block, _Block("delta_logvar", 2, False, "identity", "delta_logvar")]
        mu0, sd0 = 2.0 * math.log(0.1 * y_scale), 2.5  # intercept prior; slope N(0, 1)
        init, n_white = [0.0, mu0, 0.0], 2
        Q = np.column_stack([np.ones(n), z, z * z, y, a, z * y, z * a, y * y, y * a, a * a])
        # normal-prior constants, -n/2 log 2π and -1/2 log det S0 = -log(coef_var)
        c_const = -_LOG2PI - math.log(sd0) - n * _LOG2PI / 2 - math.log(coef_var)
        prec0 = 1.0 / coef_var

        Bt = np.vstack([np.ones(n), z]).T.copy()

        def core(vec: np.ndarray) -> float:
            u, lp = e_terms(vec[0])
            c0, c1 = vec[1], vec[2]
            d = s2 + np.exp(Bt @ vec[1:3])
            s1, sz, szz, sy, sa, szy, sza, syy, sya, saa = ((1.0 / d) @ Q).tolist()
            wr, wzr = sy - u * sa, szy - u * sza
            A11, A22 = prec0 + s1, prec0 + szz
            det = A11 * A22 - sz * sz
            quad = syy - 2 * u * sya + u * u * saa
            quad -= (A22 * wr * wr - 2.0 * sz * wr * wzr + A11 * wzr * wzr) / det
            logdet = float(np.log(d).sum()) + math.log(det)
            prior_lp = -0.5 * ((c0 - mu0) / sd0) ** 2 - 0.5 * c1 * c1
            return lp + c_const + prior_lp - 0.5 * (logdet + quad)

    else:  # M4, M5: marginal GP likelihood N(G, η² k_SE + B S0 Bᵀ (+ M5 term) + (σ² + j) I)
        B = np.column_stack([np.ones(n), z])
        C0 = coef_var * (B @ B.T) + (s2 + GP_JITTER) * np.eye(n)
        D2 = np.subtract.outer(x, x) ** 2
        ls_prior = _invgamma_log(4.0, 2.0 * span)
        eta_prior = _halfnormal_log(y_scale)
        gp_blocks = [
            _Block("delta_ls_log__", 1, False, "log", "delta_ls"),
            _Block("delta_eta_log__", 1, True, "log", "delta_eta"),
        ]
        dims["delta_ls"] = ["gp_input"]
        init_gp = [math.log(2.0 * span / 5.0), math.log(y_scale)]  # InvGamma mode, sd(y)
        n_white = 2
        if label == "M4":
            blocks, init = [E_block, *gp_blocks], [0.0, *init_gp]

            def core(vec: np.ndarray) -> float:
                u, lp = e_terms(vec[0])
                ls, eta = math.exp(vec[1]), math.exp(vec[2])
                K = C0 + (eta * eta) * np.exp((-0.5 / (ls * ls)) * D2)
                return lp + ls_prior(vec[1]) + eta_prior(vec[2]) + _gauss_chol(y - u * a, K)

        else:
            same = (D2 == 0.0).astype(float)  # 1[t = t'] with t = x
            w1_prior = _halfnormal_log(y_scale**2)
            w2_prior = _halfnormal_log(5.0 / span)
            blocks = [
                E_block,
                _Block("delta_w1_log__", 1, True, "log", "delta_w1"),
                _Block("delta_w2_log__", 1, True, "log", "delta_w2"),
                *gp_blocks,
            ]
            init = [0.0, math.log(y_scale**2), math.log(1.0 / span), *init_gp]

            def core(vec: np.ndarray) -> float:
                u, lp = e_terms(vec[0])
                v1, v2, vl, ve = vec[1], vec[2], vec[3], vec[4]
                ls, eta = math.exp(vl), math.exp(ve)
                K = C0 + (eta * eta) * np.exp((-0.5 / (ls * ls)) * D2)
                K += (math.exp(v1) * np.exp(-math.exp(v2) * x))[:, None] * same
                priors = w1_prior(v1) + w2_prior(v2) + ls_prior(vl) + eta_prior(ve)
                return lp + priors + _gauss_chol(y - u * a, K)

    k = sum(b.size for b in blocks)
    if white and n_white:
        blocks.append(_Block(white_name, n_white, False, "white", white_name))
        dims[white_name] = [f"{white_name}_dim"]
        init = [*init, *([0.0] * n_white)]
        c_white = -0.5 * n_white * _LOG2PI

        def logp(vec: np.ndarray) -> float:
            w = vec[k:]
            return core(vec) + c_white - 0.5 * float(w @ w)

    else:
        logp = core
    names = tuple(b.value if b.scalar else f"{b.value}[{i}]" for b in blocks for i in range(b.size))
    return NumpyPosterior(
        label, logp, names, tuple(blocks), np.asarray(init, float), (lo, hi), dims
    )


def _gauss_chol(r: np.ndarray, K: np.ndarray) -> float:
    """log N(r; 0, K) by LAPACK Cholesky; ``-inf`` when K is not positive definite."""
    L, info = dpotrf(K, lower=1, clean=0)
    if info != 0:
        return -math.inf
    alpha, _ = dtrtrs(L, r, lower=1)
    logdet = 2.0 * float(np.log(np.diagonal(L)).sum())
    return -0.5 * (r.size * _LOG2PI + logdet + float(alpha @ alpha))


# ------------------------------------------------------------------------------- sampler
def find_starts(
    logp: Callable[[np.ndarray], float],
    init: np.ndarray,
    chains: int,
    seed: int,
    *,
    spread: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MAP, a Laplace covariance and over-dispersed chain starting points.

    The MAP is found with BFGS (then Nelder–Mead from there) on ``-logp`` from ``init``;
    the covariance is the inverse of the central-difference Hessian there, with
    eigenvalues clipped to variances in ``[1e-10, 4]`` (flat or non-concave directions
    get sd 2).  Chain ``c`` starts at ``MAP + spread · chol(cov) · z_c``, ``z_c`` standard
    normal, redrawn (with halved spread) until ``logp`` is finite.

    Parameters
    ----------
    logp : callable
        Log density of a 1-D vector.
    init : numpy.ndarray
        Where the optimisation starts.
    chains : int
        Number of starting points.
    seed : int
        Seed of the jitter.
    spread : float
        Jitter in units of the Laplace standard deviations.

    Returns
    -------
    starts : numpy.ndarray
        ``(chains, d)`` starting points.
    mode : numpy.ndarray
        The MAP.
    cov : numpy.ndarray
        ``(d, d)`` Laplace covariance (also a good initial proposal covariance).
    """

    def neg(v: np.ndarray) -> float:
        try:
            value = logp(v)
        except ArithmeticError:
            return 1e300
        return -value if np.isfinite(value) else 1e300

    init = np.asarray(init, dtype=float)
    res = minimize(neg, init, method="BFGS")
    res = minimize(neg, res.x, method="Nelder-Mead", options={"xatol": 1e-8, "fatol": 1e-10})
    mode = res.x
    d = mode.size
    h = 1e-4
    H = np.empty((d, d))
    f0 = neg(mode)
    eye = np.eye(d) * h
    for i in range(d):
        for j in range(i, d):
            if i == j:
                H[i, i] = (neg(mode + eye[i]) - 2 * f0 + neg(mode - eye[i])) / h**2
            else:
                pp = neg(mode + eye[i] + eye[j])
                pm_ = neg(mode + eye[i] - eye[j])
                mp = neg(mode - eye[i] + eye[j])
                mm = neg(mode - eye[i] - eye[j])
                H[i, j] = H[j, i] = (pp - pm_ - mp + mm) / (4 * h**2)
    lam, V = np.linalg.eigh(H)
    var = np.clip(1.0 / np.where(lam > 0, lam, 1e-300), 1e-10, 4.0)
    cov = (V * var) @ V.T
    chol = np.linalg.cholesky(cov)
    rng = np.random.default_rng([seed, 7919])
    starts = np.empty((chains, d))
    for c in range(chains):
        scale = spread
        for _ in range(60):
            cand = mode + scale * chol @ rng.standard_normal(d)
            if neg(cand) < 1e300:
                break
            scale *= 0.5
        else:  # pragma: no cover - the mode itself is finite
            cand = mode.copy()
        starts[c] = cand
    return starts, mode, cov


@dataclass
class RWMResult:
    """Output of :func:`random_walk_metropolis`.

    Attributes
    ----------
    idata : arviz.InferenceData
        ``posterior`` (constrained named variables, dims ``chain``/``draw``) and
        ``sample_stats`` (``lp``, ``accepted``).
    sampling_s : float
        Wall seconds of tuning plus kept draws, all chains (run one after another).
    tune_s, draw_s : float
        The two parts of :attr:`sampling_s`.
    accept_rate : float
        Acceptance rate of the kept draws (all chains).
    accept_per_chain : list of float
        The same per chain.
    step_cov : list of numpy.ndarray
        The fixed proposal covariance of each chain after tuning.
    cpu_s : float
        Process CPU seconds of the same span as :attr:`sampling_s` (less sensitive than
        wall time to other jobs on a shared machine).
    setup_s : float
        Seconds spent before sampling (filled by :func:`run_baseline`: building the log
        posterior, MAP, Hessian, starting points).
    """

    idata: az.InferenceData
    sampling_s: float
    tune_s: float
    draw_s: float
    accept_rate: float
    accept_per_chain: list[float]
    step_cov: list[np.ndarray]
    cpu_s: float = math.nan
    setup_s: float = 0.0


def _walk(
    logp: Callable[[np.ndarray], float],
    x: np.ndarray,
    lp: float,
    steps: np.ndarray,
    log_u: np.ndarray,
    out: np.ndarray,
    out_lp: np.ndarray,
    out_acc: np.ndarray,
) -> tuple[np.ndarray, float]:
    """Metropolis steps with pre-drawn increments; writes the states into ``out``."""
    for i in range(steps.shape[0]):
        prop = x + steps[i]
        try:
            lp_prop = logp(prop)
        except ArithmeticError:  # math.exp overflow far in the tails: zero density
            lp_prop = -math.inf
        if lp_prop - lp >= log_u[i]:  # NaN/-inf proposals are rejected
            x, lp = prop, lp_prop
            out_acc[i] = True
        out[i] = x
        out_lp[i] = lp
    return x, lp


def random_walk_metropolis(
    logp: Callable[[np.ndarray], float],
    x0: np.ndarray,
    *,
    draws: int = 250_000,
    tune: int = 20_000,
    chains: int = 2,
    seed: int = 0,
    proposal_cov: np.ndarray | None = None,
    to_constrained: Callable[[np.ndarray], dict[str, np.ndarray]] | None = None,
    dims: dict[str, list[str]] | None = None,
    window: int = 500,
    block: int = 50_000,
) -> RWMResult:
    """Adaptive-then-fixed Gaussian random-walk Metropolis, chains run one after another.

    Tuning runs in windows of ``window`` iterations with proposal ``N(0, λ² Σ)``.  Σ
    starts at ``proposal_cov`` (identity × 0.01 if None); from the second window on it
    is replaced after every window by the empirical covariance of the second half of the
    chain's tuning iterations so far (skipped if singular).  ``log λ`` starts at
    ``log(2.38 / √d)``, is reset there when Σ first becomes empirical, and moves by
    ``3 (a_w - a*) / √(w + 1)`` after window ``w`` with acceptance ``a_w``, target
    ``a* = 0.44`` for d = 1 and 0.234 otherwise.  After tuning the proposal is fixed, so
    the kept draws are a valid (time-homogeneous) Metropolis chain.  Increments and
    log-uniforms are drawn in blocks.

    Parameters
    ----------
    logp : callable
        Log density of a 1-D float vector (``-inf``, NaN or an ``ArithmeticError``
        such as a ``math.exp`` overflow rejects).
    x0 : numpy.ndarray
        ``(chains, d)`` starting points, or one ``(d,)`` point for all chains.
    draws, tune : int
        Kept and tuning iterations per chain.
    chains : int
        Number of chains.
    seed : int
        Seed; chain ``c`` uses ``default_rng([seed, c])``.
    proposal_cov : numpy.ndarray, optional
        Initial proposal covariance (e.g. the Laplace covariance at the MAP).
    to_constrained : callable, optional
        Maps ``(chains, draws, d)`` coordinates to named arrays for the posterior group;
        default a single variable ``"x"``.
    dims : dict, optional
        ArviZ dims of the named variables.
    window : int
        Length of an adaptation window.
    block : int
        Iterations per block of pre-drawn random numbers during the kept draws.

    Returns
    -------
    RWMResult
    """
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    d = x0.shape[1]
    if x0.shape[0] == 1:
        x0 = np.repeat(x0, chains, axis=0)
    if x0.shape[0] != chains:
        raise ValueError(f"x0 has {x0.shape[0]} rows for {chains} chains")
    target = 0.44 if d == 1 else 0.234
    cov0 = np.eye(d) * 0.01 if proposal_cov is None else np.asarray(proposal_cov, float)
    samples = np.empty((chains, draws, d))
    lps = np.empty((chains, draws))
    accepted = np.zeros((chains, draws), dtype=bool)
    tune_s = draw_s = 0.0
    cpu0 = time.process_time()
    covs = []
    for c in range(chains):
        rng = np.random.default_rng([seed, c])
        x = x0[c].copy()
        lp = float(logp(x))
        if not np.isfinite(lp):
            raise ValueError(f"chain {c} starts where logp is not finite: {x}")
        chol = np.linalg.cholesky(cov0)
        log_lam = math.log(2.38 / math.sqrt(d))
        t0 = time.perf_counter()
        trace = np.empty((max(tune, 1), d))
        trace_lp = np.empty(max(tune, 1))
        trace_acc = np.zeros(max(tune, 1), dtype=bool)
        done, w, empirical = 0, 0, False
        while done < tune:
            m = min(window, tune - done)
            steps = rng.standard_normal((m, d)) @ (math.exp(log_lam) * chol).T
            log_u = np.log(rng.random(m))
            sl = slice(done, done + m)
            x, lp = _walk(logp, x, lp, steps, log_u, trace[sl], trace_lp[sl], trace_acc[sl])
            done += m
            log_lam += 3.0 * (float(trace_acc[sl].mean()) - target) / math.sqrt(w + 1)
            w += 1
            if w >= 2 and done < tune:
                emp = np.cov(trace[done // 2 : done], rowvar=False).reshape(d, d)
                try:
                    chol = np.linalg.cholesky(emp)
                except np.linalg.LinAlgError:
                    continue
                if not empirical:  # λ was sized for Σ0's scale
                    log_lam, empirical = math.log(2.38 / math.sqrt(d)), True
        t1 = time.perf_counter()
        step_chol = math.exp(log_lam) * chol
        covs.append(step_chol @ step_chol.T)
        for start in range(0, draws, block):
            m = min(block, draws - start)
            steps = rng.standard_normal((m, d)) @ step_chol.T
            log_u = np.log(rng.random(m))
            sl = slice(start, start + m)
            x, lp = _walk(logp, x, lp, steps, log_u, samples[c, sl], lps[c, sl], accepted[c, sl])
        t2 = time.perf_counter()
        tune_s += t1 - t0
        draw_s += t2 - t1
    cpu_s = time.process_time() - cpu0
    posterior = {"x": samples} if to_constrained is None else to_constrained(samples)
    idata = az.from_dict(
        posterior=posterior,
        sample_stats={"lp": lps, "accepted": accepted},
        dims=dims,
        attrs={"sampler": "random_walk_metropolis", "tune": tune, "draws": draws},
    )
    per_chain = accepted.mean(axis=1).tolist()
    return RWMResult(
        idata=idata,
        sampling_s=tune_s + draw_s,
        tune_s=tune_s,
        draw_s=draw_s,
        accept_rate=float(accepted.mean()),
        accept_per_chain=per_chain,
        step_cov=covs,
        cpu_s=cpu_s,
    )


def summarize_E(idata: az.InferenceData, wall_s: float, var: str = "E") -> dict[str, float]:
    """ESS (bulk, tail), ESS per second, r̂, mean, sd and MCSE of the mean of one variable.

    Parameters
    ----------
    idata : arviz.InferenceData
        With a ``posterior`` group holding ``var`` with dims ``(chain, draw)``.
    wall_s : float
        Sampling wall seconds used for ``ess_per_s_E``.
    var : str
        Variable name.

    Returns
    -------
    dict
        ``ess_bulk_E``, ``ess_tail_E``, ``ess_per_s_E``, ``rhat_E``, ``mean_E``,
        ``sd_E``, ``mcse_mean_E``.
    """
    post = idata.posterior[var]
    ess_bulk = float(az.ess(idata, var_names=[var], method="bulk")[var])
    ess_tail = float(az.ess(idata, var_names=[var], method="tail")[var])
    return {
        "ess_bulk_E": ess_bulk,
        "ess_tail_E": ess_tail,
        "ess_per_s_E": ess_bulk / wall_s if wall_s > 0 else math.nan,
        "rhat_E": float(az.rhat(idata, var_names=[var])[var]),
        "mean_E": float(post.mean()),
        "sd_E": float(post.std()),
        "mcse_mean_E": float(az.mcse(idata, var_names=[var], method="mean")[var]),
    }


def run_baseline(
    label: str,
    *,
    draws: int = 250_000,
    tune: int = 20_000,
    chains: int = 2,
    seed: int = 2026,
    white: bool = False,
    data: CalibrationData | None = None,
    return_result: bool = False,
) -> dict[str, Any] | tuple[dict[str, Any], RWMResult]:
    """Random-walk Metropolis on one formulation's numpy posterior; the benchmark row.

    Setup (timed separately as ``setup_s``) builds the numpy log posterior, finds the
    MAP and the Laplace covariance, and draws over-dispersed starts (MAP + 2 Laplace sd
    jitter, see :func:`find_starts`); the Laplace covariance is the initial proposal.

    Parameters
    ----------
    label : str
        ``"M0"`` ... ``"M5"``.
    draws, tune, chains, seed :
        As for :func:`random_walk_metropolis`.
    white : bool
        Also sample the whitened coefficient coordinates (see module docstring).
    data : CalibrationData, optional
        Default :func:`load_beam_data`.
    return_result : bool
        Also return the :class:`RWMResult`.

    Returns
    -------
    dict
        ``formulation``, ``sampler``, ``dim``, ``draws``, ``tune``, ``chains``,
        ``wall_s`` (tuning + kept draws), ``cpu_s`` (its process CPU time), ``tune_s``,
        ``draw_s``, ``setup_s``, ``ess_bulk_E``, ``ess_tail_E``, ``ess_per_s_E``
        (= ess_bulk / wall_s), ``rhat_E``, ``mean_E``, ``sd_E``, ``mcse_mean_E``,
        ``ess_per_cpu_s_E``, ``accept_rate``, ``us_per_iter``.
    """
    t0 = time.perf_counter()
    post = numpy_log_posterior(label, data, white=white)
    starts, _, cov = find_starts(post.logp, post.init, chains, seed)
    setup_s = time.perf_counter() - t0
    res = random_walk_metropolis(
        post.logp,
        starts,
        draws=draws,
        tune=tune,
        chains=chains,
        seed=seed,
        proposal_cov=cov,
        to_constrained=post.to_constrained,
        dims=post.dims,
    )
    res.setup_s = setup_s
    summary = summarize_E(res.idata, res.sampling_s)
    row: dict[str, Any] = {
        "formulation": label,
        "sampler": "rwm" + ("+white" if white else ""),
        "dim": post.ndim,
        "draws": draws,
        "tune": tune,
        "chains": chains,
        "wall_s": res.sampling_s,
        "cpu_s": res.cpu_s,
        "tune_s": res.tune_s,
        "draw_s": res.draw_s,
        "setup_s": setup_s,
        **summary,
        "ess_per_cpu_s_E": summary["ess_bulk_E"] / res.cpu_s,
        "accept_rate": res.accept_rate,
        "us_per_iter": 1e6 * res.sampling_s / (chains * (draws + tune)),
    }
    return (row, res) if return_result else row


def _main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Random-walk Metropolis baselines, beam M0-M5.")
    parser.add_argument("labels", nargs="*", default=list(LABELS))
    parser.add_argument("--draws", type=int, default=250_000)
    parser.add_argument("--tune", type=int, default=20_000)
    parser.add_argument("--chains", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--white", action="store_true", help="also sample *_white coordinates")
    parser.add_argument("--json", type=Path, help="write the rows as JSON here")
    args = parser.parse_args(argv)
    rows = []
    for label in args.labels:
        row = run_baseline(
            label,
            draws=args.draws,
            tune=args.tune,
            chains=args.chains,
            seed=args.seed,
            white=args.white,
        )
        rows.append(row)
        print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}))
    frame = pd.DataFrame(rows).set_index("formulation")
    cols = ["dim", "wall_s", "cpu_s", "setup_s", "ess_bulk_E", "ess_tail_E", "ess_per_s_E"]
    cols += ["ess_per_cpu_s_E", "rhat_E"]
    cols += ["accept_rate", "mean_E", "sd_E", "mcse_mean_E", "us_per_iter"]
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        print(frame[cols].round(4).to_string())
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
