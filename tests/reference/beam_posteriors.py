"""Reference log posteriors of the beam formulations M0–M5 in plain numpy/scipy.

For each beam formulation (:func:`beam_formulations`) :func:`numpy_log_posterior` writes
the log posterior of ``kohpymc.build_model(beam.physics_model(), data, formulation)`` in
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

These are independent references for the tests and the posteriors the random-walk
Metropolis baseline of ``benchmarks/baselines.py`` samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.linalg.lapack import dpotrf, dtrtrs
from scipy.special import expit, gammaln

import kohpymc as kp
from kohpymc.examples import beam

__all__ = [
    "DATA_PATH",
    "GP_JITTER",
    "LABELS",
    "NumpyPosterior",
    "beam_formulations",
    "load_beam_data",
    "numpy_log_posterior",
]

DATA_PATH = Path(beam.__file__).parent / "data" / "beam_calibration.csv"
LABELS = ("M0", "M1", "M2", "M3", "M4", "M5")
#: jitter ``pm.gp.Marginal.marginal_likelihood`` adds to the diagonal (PyMC's default)
GP_JITTER = 1e-6
_LOG2PI = math.log(2.0 * math.pi)


def load_beam_data(path: str | Path = DATA_PATH) -> kp.CalibrationData:
    """The beam calibration data (20 rows at P = 2.5) with known noise sd ``sqrt(0.1)``.

    Parameters
    ----------
    path : str or Path
        CSV with columns ``x``, ``P``, ``u``.

    Returns
    -------
    CalibrationData
    """
    return kp.CalibrationData.from_csv(
        path, inputs=["x", "P"], output="u", noise_sd=math.sqrt(beam.NOISE_VAR)
    )


def beam_formulations() -> dict[str, Any]:
    """M0–M4 of :func:`kohpymc.examples.beam.formulations` plus M5 (non-stationary GP on x).

    Returns
    -------
    dict
        Label -> discrepancy formulation.
    """
    forms = beam.formulations()
    forms["M5"] = kp.NonStationaryGP(["x"], time="x", mean=["x"])
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
    label: str, data: kp.CalibrationData | None = None, *, white: bool = True
) -> NumpyPosterior:
    """The log posterior of one beam formulation in numpy, on PyMC's coordinates.

    Reimplements ``kohpymc.build_model(beam.physics_model(), data, form)`` for
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
