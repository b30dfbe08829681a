r"""Scale benchmark: a GP-discrepancy calibration on 9,120 points without a dense Cholesky.

Design (the size of the paper's full dielectric-charging set): 12 (V, T) settings,
V ∈ {10, 20, 30} V × T ∈ {300, 330, 360, 390} K, 190 times ``t_k = 100 k / 190`` s and
4 replicates per (V, T, t): ``n = 9,120`` raw points, 2,280 unique inputs.

Physics (cheap and analytic, written in PyTensor so NUTS gets autodiff gradients)::

    G(V, T, t; A, τ_300, E_a) = A (V / 10)² exp(-t / τ(T)),
    τ(T) = τ_300 exp(E_a / k_B (1/T - 1/300))                          (Arrhenius)

with uniform priors ``A ~ U(0.5, 5)``, ``τ_300 ~ U(5, 100)`` s, ``E_a ~ U(0.05, 0.5)`` eV.
Truth: G at (2, 30, 0.2) plus a polarization-like discrepancy
``0.6 (V/10) exp(-t / τ_p(T))``, ``τ_p(T) = 40 exp(0.1 eV / k_B (1/T - 1/300))`` s, plus
N(0, 0.2²) noise (σ known), seed fixed.

Model::

    y_ijkr = G(V_i, T_j, t_k; θ) + δ(V_i, T_j, t_k) + ε_ijkr,   ε ~ N(0, σ²) iid
    δ ~ GP(0, η² k_V(V, V'; ℓ_V) k_T(T, T'; ℓ_T) k_t(t, t'; ℓ_t))   (zero mean)

``k_·`` squared-exponential on raw inputs, ``ℓ_· ~ InverseGamma(4, 2 · span)`` (kohpymc's
default), ``η ~ HalfNormal(sd(y))``.

Exact structure used
--------------------
1. **Replicate reduction.**  For one unique input ``u`` with replicates ``y_u1..y_ur`` and
   latent value ``f_u = G_u + δ_u``, ``Σ_k (y_uk - f_u)² = S_u + r (ȳ_u - f_u)²`` with
   ``S_u = Σ_k (y_uk - ȳ_u)²``, so

   ``Π_k N(y_uk | f_u, σ²) = N(ȳ_u | f_u, σ²/r) · (2πσ²)^{-(r-1)/2} r^{-1/2} exp(-S_u / 2σ²)``.

   Integrating δ out, ``p(y | θ, η, ℓ) = N(ȳ | G(θ), K + (σ²/r) I) · C(y, σ)`` with
   ``log C = Σ_u [-(r-1)/2 log(2πσ²) - ½ log r - S_u / (2σ²)]``: C involves neither θ nor
   the GP, so the 9,120-point likelihood is the 2,280-point one on the means times a
   constant (:func:`replicate_constant`; it is added to the potential so that the model's
   log-likelihood is the raw-data one, to rounding).
2. **Kronecker.**  The means lie on the full grid V(3) × T(4) × t(190), so
   ``K = η² K_V ⊗ K_T ⊗ K_t``.  With ``K_· = Q_· diag(λ_·) Q_·ᵀ``,
   ``K + s² I = Q diag(η² λ_V ⊗ λ_T ⊗ λ_t + s²) Qᵀ`` (``Q = Q_V ⊗ Q_T ⊗ Q_t``), so the
   quadratic form and the log-determinant cost one 190×190 and two tiny eigh plus
   mode products (:func:`kron_gp_loglik`).
3. **Gradient.**  Differentiating through ``eigh`` involves ``1 / (λ_i - λ_j)``, which is
   ill-conditioned here (a smooth 190×190 SE kernel has dozens of eigenvalues at the
   1e-15 rounding floor) and slow (PyTensor's ``EighGrad`` is a Python op: 175 ms per
   call for the 190×190 factor).  :func:`kron_gp_loglik` instead supplies the analytic
   gradient ``∂L/∂p = ½ (αᵀ ∂K/∂p α - tr(K⁻¹ ∂K/∂p))``, ``∂L/∂r = -α``, where both terms
   are again Kronecker/diagonal in the eigenbasis, through an inlined ``OpFromGraph``
   with ``lop_overrides``.  Everything stays in PyTensor, so ``mode="NUMBA"`` compiles it.

Check: on a 1,920-point subset (12 settings × 40 times × 4 replicates) the structured
posterior draws are importance-weighted by ``p_exact / p_structured``, ``p_exact`` from
the dense 1,920×1,920 covariance (replicates as separate rows, scipy Cholesky).

Run ``python benchmarks/scale.py [--quick]``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import logging
import sys
import time
import warnings
from dataclasses import dataclass
from typing import Any

import arviz as az
import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
import scipy.linalg

from kohpymc.kronecker import kron_gp_loglik

#: Boltzmann constant, eV/K
KB = 8.617333262e-5
VOLTAGES = np.array([10.0, 20.0, 30.0])
TEMPERATURES = np.array([300.0, 330.0, 360.0, 390.0])
N_TIMES = 190
N_REPLICATES = 4
T_END = 100.0
NOISE_SD = 0.2
#: uniform prior bounds of the physics parameters
PRIORS: dict[str, tuple[float, float]] = {
    "A": (0.5, 5.0),
    "tau300": (5.0, 100.0),
    "E_a": (0.05, 0.5),
}
TRUE_PARAMS: dict[str, float] = {"A": 2.0, "tau300": 30.0, "E_a": 0.2}
PHYSICS_NAMES = tuple(PRIORS)
GP_NAMES = ("eta", "ls")
SEED = 20260


def _log(msg: str) -> None:
    print(f"[scale {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _quiet() -> None:
    warnings.filterwarnings("ignore", message="PyTensor could not link to a BLAS")
    warnings.filterwarnings("ignore", message=".*os.fork\\(\\) was called.*")
    warnings.filterwarnings("ignore", message="The effect of Potentials")
    logging.getLogger("pytensor.tensor.blas").setLevel(logging.ERROR)
    logging.getLogger("pymc").setLevel(logging.ERROR)


# --------------------------------------------------------------------------- data


def times(n_times: int = N_TIMES) -> np.ndarray:
    """Equally spaced times ``100 k / n_times``, k = 1..n_times (s)."""
    return T_END * np.arange(1, n_times + 1) / n_times


def physics(V: Any, T: Any, t: Any, A: Any, tau300: Any, E_a: Any, xp: Any = np) -> Any:
    """Decaying charging current ``A (V/10)² exp(-t/τ(T))`` with Arrhenius ``τ(T)``.

    ``xp`` is ``numpy`` or ``pytensor.tensor`` (anything with ``exp``); inputs broadcast.

    Examples
    --------
    >>> round(float(physics(20.0, 300.0, 30.0, 2.0, 30.0, 0.2)), 4)
    2.9430
    """
    tau = tau300 * xp.exp(E_a / KB * (1.0 / T - 1.0 / 300.0))
    return A * (V / 10.0) ** 2 * xp.exp(-t / tau)


def discrepancy(V: Any, T: Any, t: Any) -> np.ndarray:
    """The effect missing from :func:`physics`: a slower polarization-like decay."""
    tau_p = 40.0 * np.exp(0.1 / KB * (1.0 / T - 1.0 / 300.0))
    return 0.6 * (V / 10.0) * np.exp(-t / tau_p)


@dataclass(frozen=True)
class GridData:
    """Replicated measurements on a full (V, T, t) grid.

    Attributes
    ----------
    grids : tuple of ndarray
        The 1-D axes ``(V, T, t)``.
    y : ndarray
        Measurements, shape ``(n_V, n_T, n_t, r)``.
    sigma : float
        Known noise sd.
    """

    grids: tuple[np.ndarray, np.ndarray, np.ndarray]
    y: np.ndarray
    sigma: float

    @property
    def n(self) -> int:
        """Number of raw points."""
        return int(self.y.size)

    @property
    def n_unique(self) -> int:
        """Number of unique inputs."""
        return int(np.prod(self.y.shape[:-1]))

    @property
    def replicates(self) -> int:
        """Replicates per unique input."""
        return int(self.y.shape[-1])

    @property
    def ybar(self) -> np.ndarray:
        """Replicate means, shape ``(n_V, n_T, n_t)``."""
        return self.y.mean(axis=-1)

    def mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Broadcastable ``(V, T, t)`` of shapes ``(n_V,1,1), (1,n_T,1), (1,1,n_t)``."""
        V, T, t = self.grids
        return V[:, None, None], T[None, :, None], t[None, None, :]

    def raw_inputs(self) -> np.ndarray:
        """``(n, 3)`` raw inputs, one row per replicate (order V, T, t, replicate)."""
        V, T, t = self.grids
        r = self.replicates
        m = np.stack(np.meshgrid(V, T, t, np.arange(r), indexing="ij"), axis=-1)
        return m[..., :3].reshape(-1, 3)

    def subset(self, time_index: np.ndarray) -> GridData:
        """The same settings and replicates at a subset of the times."""
        V, T, t = self.grids
        return GridData((V, T, t[time_index]), self.y[:, :, time_index, :], self.sigma)


def simulate(
    n_times: int = N_TIMES,
    n_replicates: int = N_REPLICATES,
    noise: float = NOISE_SD,
    seed: int = SEED,
) -> GridData:
    """Synthetic truth ``physics(θ*) + discrepancy + N(0, noise²)`` on the full design.

    Examples
    --------
    >>> d = simulate()
    >>> d.n, d.n_unique, d.y.shape
    (9120, 2280, (3, 4, 190, 4))
    """
    grids = (VOLTAGES.copy(), TEMPERATURES.copy(), times(n_times))
    V, T, t = grids[0][:, None, None], grids[1][None, :, None], grids[2][None, None, :]
    f = physics(V, T, t, **TRUE_PARAMS) + discrepancy(V, T, t)
    rng = np.random.default_rng(seed)
    y = f[..., None] + rng.normal(0.0, noise, size=f.shape + (n_replicates,))
    return GridData(grids, y, float(noise))


def subset_times(n_full: int = N_TIMES, n_sub: int = 40) -> np.ndarray:
    """``n_sub`` indices spread evenly over ``range(n_full)``."""
    return np.unique(np.round(np.linspace(0, n_full - 1, n_sub)).astype(int))


# --------------------------------------------------------------------------- likelihood


def replicate_constant(data: GridData) -> float:
    """``log C``: the raw-data log-likelihood minus the one of the replicate means.

    ``Σ_u [-(r-1)/2 log(2πσ²) - ½ log r - S_u / (2σ²)]``, ``S_u`` the within-replicate sum
    of squares; independent of θ and of the GP.
    """
    r, s2 = data.replicates, data.sigma**2
    ss = float(((data.y - data.y.mean(axis=-1, keepdims=True)) ** 2).sum())
    n_u = data.n_unique
    return float(
        -0.5 * (r - 1) * n_u * np.log(2 * np.pi * s2) - 0.5 * n_u * np.log(r) - ss / (2 * s2)
    )


def dense_loglik(data: GridData, params: dict[str, Any], jitter: float = 0.0) -> float:
    """The exact GP log-likelihood of the raw data from the dense ``n × n`` covariance.

    Every replicate is its own row: ``Σ = η² k(x_i, x_j) + σ² I`` (numpy/scipy Cholesky).
    """
    X = data.raw_inputs()
    y = data.y.reshape(-1)
    G = physics(X[:, 0], X[:, 1], X[:, 2], *(params[k] for k in PHYSICS_NAMES))
    ls = np.asarray(params["ls"], dtype=float)
    K = np.ones((len(y), len(y)))
    for k in range(3):
        K *= np.exp(-0.5 * (X[:, k, None] - X[None, :, k]) ** 2 / ls[k] ** 2)
    K *= float(params["eta"]) ** 2
    K[np.diag_indices_from(K)] += data.sigma**2 + jitter
    L = scipy.linalg.cholesky(K, lower=True, check_finite=False)
    z = scipy.linalg.solve_triangular(L, y - G, lower=True, check_finite=False)
    return float(-0.5 * z @ z - np.log(np.diag(L)).sum() - 0.5 * len(y) * np.log(2 * np.pi))


# --------------------------------------------------------------------------- model


def build_model(data: GridData) -> pm.Model:
    """PyMC model: uniform physics priors, GP hyperpriors, structured GP potential.

    The deterministic ``loglik`` is the full raw-data log-likelihood (structured GP on
    the replicate means plus :func:`replicate_constant`).
    """
    V, T, t = data.mesh()
    spans = np.array([np.ptp(g) for g in data.grids])
    with pm.Model() as model:
        theta = {k: pm.Uniform(k, lower=lo, upper=hi) for k, (lo, hi) in PRIORS.items()}
        eta = pm.HalfNormal("eta", sigma=float(data.y.std()))
        ls = pm.InverseGamma("ls", alpha=4.0, beta=2.0 * spans, shape=3)
        G = physics(V, T, t, theta["A"], theta["tau300"], theta["E_a"], xp=pt)
        resid = pt.as_tensor_variable(data.ybar) - G
        ll = kron_gp_loglik(resid, data.grids, eta, ls, data.sigma**2 / data.replicates)
        ll = ll + replicate_constant(data)
        pm.Potential("gp_loglik", ll)
        pm.Deterministic("loglik", ll)
    return model


def grad_eval_time(model: pm.Model, mode: str | None, n_evals: int = 200) -> dict[str, float]:
    """Compile time and mean time of one logp+gradient evaluation in ``mode``."""
    t0 = time.perf_counter()
    fn = model.logp_dlogp_function(ravel_inputs=True, mode=mode)
    fn.set_extra_values({})
    x0 = model.initial_point()
    q = np.concatenate([np.ravel(x0[v.name]) for v in model.value_vars])
    fn(q)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(n_evals):
        fn(q)
    return {"compile_s": compile_s, "eval_ms": 1e3 * (time.perf_counter() - t0) / n_evals}


def laplace_start(
    fn: Any, q0: np.ndarray, h: float = 1e-4
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Posterior mode and Laplace covariance in the sampler's (transformed) space.

    L-BFGS on ``-logp`` from ``q0``, then a central finite-difference Hessian from
    ``2 d`` gradient evaluations (``d`` = number of free parameters).
    """
    import scipy.optimize

    def neg(q: np.ndarray) -> tuple[float, np.ndarray]:
        lp, g = fn(q)
        return -float(lp), -np.asarray(g, dtype=float)

    res = scipy.optimize.minimize(neg, q0, jac=True, method="L-BFGS-B")
    q_map = res.x
    d = len(q_map)
    H = np.empty((d, d))
    for i in range(d):
        e = np.zeros(d)
        e[i] = h
        H[i] = (neg(q_map + e)[1] - neg(q_map - e)[1]) / (2 * h)
    H = 0.5 * (H + H.T)
    try:
        cov = np.linalg.inv(H)
        if not np.all(np.linalg.eigvalsh(cov) > 0):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        cov = np.diag(1.0 / np.clip(np.diag(H), 1e-8, None))
    return q_map, cov, {"nfev": int(res.nfev), "success": bool(res.success)}


def sample(
    model: pm.Model,
    *,
    draws: int,
    tune: int,
    mode: str | None = "NUMBA",
    cores: int = 1,
    seed: int = 1,
    target_accept: float = 0.9,
    laplace_init: bool = True,
) -> tuple[az.InferenceData, float]:
    """Two NUTS chains; returns the trace and the wall time (s) including compile.

    With ``laplace_init`` (default) the logp+gradient function is compiled once (in
    ``mode``), the chains start from independent draws of the Laplace approximation at
    the posterior mode (:func:`laplace_start`), and the diagonal mass matrix starts at the
    Laplace variances (weight 10 draws) instead of the identity, which saves the early
    tuning with tiny steps.  Otherwise plain ``pm.sample`` (``jitter+adapt_diag``).
    """
    t0 = time.perf_counter()
    compile_kwargs = {} if mode is None else {"mode": mode}
    if not laplace_init:
        with model:
            idata = pm.sample(
                draws=draws,
                tune=tune,
                chains=2,
                cores=cores,
                random_seed=seed,
                target_accept=target_accept,
                progressbar=False,
                compute_convergence_checks=False,
                compile_kwargs=compile_kwargs,
            )
        return idata, time.perf_counter() - t0

    from pymc.blocking import DictToArrayBijection, RaveledVars
    from pymc.step_methods.hmc.quadpotential import QuadPotentialDiagAdapt

    ip = model.initial_point()
    fn = model.logp_dlogp_function(ravel_inputs=True, initial_point=ip, **compile_kwargs)
    fn.set_extra_values({})
    q0 = DictToArrayBijection.map({v.name: ip[v.name] for v in model.value_vars})
    q_map, cov, info = laplace_start(fn, q0.data)
    _log(f"mode found ({info['nfev']} evaluations) at {time.perf_counter() - t0:.1f} s")
    rng = np.random.default_rng(seed)
    starts = [
        DictToArrayBijection.rmap(
            RaveledVars(rng.multivariate_normal(q_map, cov), q0.point_map_info)
        )
        for _ in range(2)
    ]
    potential = QuadPotentialDiagAdapt(
        len(q_map), q_map, np.diag(cov), 10, rng=np.random.default_rng(seed + 1)
    )
    with model:
        step = pm.NUTS(potential=potential, target_accept=target_accept, logp_dlogp_func=fn)
        idata = pm.sample(
            draws=draws,
            tune=tune,
            chains=2,
            cores=cores,
            step=step,
            initvals=starts,
            random_seed=seed,
            progressbar=False,
            compute_convergence_checks=False,
        )
    return idata, time.perf_counter() - t0


def diagnostics(idata: az.InferenceData) -> dict[str, Any]:
    """ESS/r̂ of the physics parameters, max r̂ over all free parameters, divergences."""
    summ = az.summary(idata, var_names=[*PHYSICS_NAMES, *GP_NAMES], round_to="none")
    phys = summ.loc[list(PHYSICS_NAMES)]
    return {
        "ess_bulk": {k: float(phys.loc[k, "ess_bulk"]) for k in PHYSICS_NAMES},
        "ess_tail": {k: float(phys.loc[k, "ess_tail"]) for k in PHYSICS_NAMES},
        "rhat_max": float(summ["r_hat"].max()),
        "divergences": int(idata.sample_stats["diverging"].sum()),
        "mean_n_steps": float(idata.sample_stats["n_steps"].mean()),
        "step_size": float(idata.sample_stats["step_size"].mean()),
        "mean": {k: float(phys.loc[k, "mean"]) for k in PHYSICS_NAMES},
        "sd": {k: float(phys.loc[k, "sd"]) for k in PHYSICS_NAMES},
        "summary": summ,
    }


def subset_check(data: GridData, idata: az.InferenceData, n_check: int) -> dict[str, Any]:
    """Importance-weight structured draws by the exact dense GP; compare physics means.

    Uses ``n_check`` draws evenly thinned from the pooled chains.  Returns the spread of
    ``log p_exact - log p_structured``, the PSIS k̂, and ``|E_w[θ] - E[θ]| / sd(θ)``.
    """
    post = az.extract(idata, var_names=[*PHYSICS_NAMES, *GP_NAMES, "loglik"])
    n_draws = post.sizes["sample"]
    idx = np.unique(np.linspace(0, n_draws - 1, min(n_check, n_draws)).astype(int))
    logw = np.empty(len(idx))
    t0 = time.perf_counter()
    for j, i in enumerate(idx):
        p = {k: post[k].values[..., i] for k in [*PHYSICS_NAMES, *GP_NAMES]}
        logw[j] = dense_loglik(data, p) - float(post["loglik"].values[i])
    dense_s = time.perf_counter() - t0
    psis_lw, khat = az.psislw(logw - logw.max())
    w = np.exp(psis_lw - psis_lw.max())
    w /= w.sum()
    delta = {}
    for k in PHYSICS_NAMES:
        x = post[k].values[idx]
        delta[k] = float(abs(np.sum(w * x) - x.mean()) / x.std())
    return {
        "n_draws_checked": len(idx),
        "logw_mean": float(logw.mean()),
        "logw_spread": float(logw.max() - logw.min()),
        "logw_sd": float(logw.std()),
        "khat": float(np.asarray(khat)),
        "delta_over_sd": delta,
        "max_delta_over_sd": max(delta.values()),
        "dense_s": dense_s,
    }


# --------------------------------------------------------------------------- driver


def run(
    quick: bool = False,
    *,
    mode: str | None = None,
    cores: int = 1,
    draws: int | None = None,
    tune: int | None = None,
    n_check: int | None = None,
    compare_modes: bool = False,
    seed: int = SEED,
) -> dict[str, Any]:
    """Run the full (n = 9,120) calibration and the n = 1,920 exact-GP subset check.

    Parameters
    ----------
    quick : bool
        Fewer draws (200 tune + 300 per chain; 100 draws in the dense check).
    mode : str or None
        PyTensor mode of the sampler's logp+gradient (None: the default C backend, which
        measured as fast per evaluation as ``"NUMBA"`` here and compiles 3× faster).
    cores : int
        ``pm.sample`` cores (1: chains run one after the other).
    draws, tune : int, optional
        Per chain; default 800 draws after 500 tuning steps.
    n_check : int, optional
        Posterior draws re-weighted with the dense GP (default 200; 100 quick).
    compare_modes : bool
        Also time one logp+gradient evaluation of the full model in C and NUMBA mode.
    seed : int
        Data seed (sampling seeds derive from it).

    Returns
    -------
    dict
        ``n``, ``n_unique``, ``wall_s``, ``compile_s``, ``sampling_s``, ``ess_bulk``,
        ``rhat_max``, ``divergences``, ``posterior_mean``/``sd``, ``subset`` (the check) and,
        with ``compare_modes``, ``eval_timing``.
    """
    _quiet()
    draws = draws or (300 if quick else 800)
    tune = tune or (200 if quick else 500)
    n_check = n_check or (100 if quick else 200)
    data = simulate(seed=seed)
    out: dict[str, Any] = {"n": data.n, "n_unique": data.n_unique, "mode": mode or "C"}
    out["draws"], out["tune"], out["cores"] = draws, tune, cores

    _log(f"n = {data.n} ({data.n_unique} unique); sampling, mode {out['mode']}")
    model = build_model(data)
    if compare_modes:
        out["eval_timing"] = {
            name: grad_eval_time(model, m) for name, m in (("C", None), ("NUMBA", "NUMBA"))
        }
    idata, wall = sample(model, draws=draws, tune=tune, mode=mode, cores=cores, seed=seed + 1)
    sampling = float(idata.posterior.attrs.get("sampling_time", np.nan))
    diag = diagnostics(idata)
    out.update(
        wall_s=wall,
        sampling_s=sampling,
        compile_s=wall - sampling,
        ess_bulk=diag["ess_bulk"],
        rhat_max=diag["rhat_max"],
        divergences=diag["divergences"],
        mean_n_steps=diag["mean_n_steps"],
        posterior_mean=diag["mean"],
        posterior_sd=diag["sd"],
    )
    out["summary_full"] = diag["summary"]
    _log(f"done in {wall:.1f} s\n{diag['summary']}")

    sub = data.subset(subset_times())
    sub_model = build_model(sub)
    sub_idata, sub_wall = sample(
        sub_model, draws=draws, tune=tune, mode=mode, cores=cores, seed=seed + 2
    )
    sub_diag = diagnostics(sub_idata)
    _log(f"subset n = {sub.n} sampled in {sub_wall:.1f} s\n{sub_diag['summary']}")
    check = subset_check(sub, sub_idata, n_check)
    check.update(
        n=sub.n,
        n_unique=sub.n_unique,
        wall_s=sub_wall,
        rhat_max=sub_diag["rhat_max"],
        divergences=sub_diag["divergences"],
        ess_bulk=sub_diag["ess_bulk"],
    )
    out["subset"] = check
    return out


def run_library(
    quick: bool = False, *, cores: int = 2, mode: str | None = "NUMBA", seed: int = SEED
) -> dict[str, Any]:
    """The same n = 9,120 calibration as one :func:`kohpymc.calibrate` call with
    :class:`kohpymc.GridGP` (the library's defaults: its GP priors, PyMC's
    ``jitter+adapt_diag`` start, the identifiability check and exact per-row LOO values).

    Returns
    -------
    dict
        ``wall_s`` (the whole call), ``sampling_s``, ``rhat_max``, ``ess_bulk``,
        ``divergences``, ``posterior_mean``/``sd`` of the physics parameters.
    """
    import kohpymc as kp

    _quiet()
    draws, tune = (300, 200) if quick else (800, 500)
    data = simulate(seed=seed)
    X = data.raw_inputs()
    cal = kp.CalibrationData(
        {"V": X[:, 0], "T": X[:, 1], "t": X[:, 2]}, data.y.reshape(-1), noise_sd=data.sigma
    )
    model = kp.PhysicsModel(
        lambda i, p: physics(i["V"], i["T"], i["t"], p["A"], p["tau300"], p["E_a"], xp=pt),
        {k: kp.Uniform(lo, hi) for k, (lo, hi) in PRIORS.items()},
        inputs=["V", "T", "t"],
        backend="pytensor",
        name="decaying_current",
    )
    _log(f"library: n = {cal.n}, kohpymc.calibrate with GridGP, mode {mode or 'C'}")
    start = time.perf_counter()
    result = kp.calibrate(
        model,
        cal,
        kp.GridGP(["V", "T", "t"], mean="zero"),
        draws=draws,
        tune=tune,
        chains=2,
        cores=cores,
        mode=mode,
        random_seed=seed + 3,
        warn=False,
    )
    idata = result.idata
    wall = time.perf_counter() - start
    names = list(PHYSICS_NAMES)
    summary = az.summary(idata, var_names=names)
    _log(f"library run done in {wall:.1f} s\n{summary}")
    return {
        "n": cal.n,
        "draws": draws,
        "tune": tune,
        "mode": mode or "C",
        "wall_s": wall,
        "sampling_s": float(idata.posterior.attrs.get("sampling_time", np.nan)),
        "rhat_max": float(summary["r_hat"].max()),
        "ess_bulk": {k: float(summary.loc[k, "ess_bulk"]) for k in names},
        "divergences": int(idata.sample_stats["diverging"].sum()),
        "posterior_mean": {k: float(idata.posterior[k].mean()) for k in names},
        "posterior_sd": {k: float(idata.posterior[k].std()) for k in names},
        "sampler_problems": result.problems,
    }


def _table(res: dict[str, Any]) -> str:
    lines = [
        f"n = {res['n']} raw points, {res['n_unique']} unique; mode {res['mode']}, "
        f"{res['cores']} core(s), 2 chains × ({res['tune']} tune + {res['draws']} draws)",
        f"wall {res['wall_s']:.1f} s = compile/init {res['compile_s']:.1f} s + sampling "
        f"{res['sampling_s']:.1f} s; r̂ max {res['rhat_max']:.4f}; "
        f"divergences {res['divergences']}; mean leapfrog steps {res['mean_n_steps']:.1f}",
        f"{'param':>8} {'true':>8} {'mean':>9} {'sd':>8} {'ess_bulk':>9}",
    ]
    for k in PHYSICS_NAMES:
        lines.append(
            f"{k:>8} {TRUE_PARAMS[k]:8.3f} {res['posterior_mean'][k]:9.4f} "
            f"{res['posterior_sd'][k]:8.4f} {res['ess_bulk'][k]:9.0f}"
        )
    s = res["subset"]
    lines += [
        f"subset n = {s['n']} ({s['n_unique']} unique): wall {s['wall_s']:.1f} s, "
        f"r̂ max {s['rhat_max']:.4f}, divergences {s['divergences']}",
        f"  exact dense GP on {s['n_draws_checked']} draws ({s['dense_s']:.1f} s): "
        f"log p_exact - log p_struct = {s['logw_mean']:.3e}, spread {s['logw_spread']:.2e}, "
        f"k̂ {s['khat']:.2f}",
        "  |Δ mean| / sd: "
        + ", ".join(f"{k} {v:.2e}" for k, v in s["delta_over_sd"].items())
        + f" (max {s['max_delta_over_sd']:.2e})",
    ]
    if "eval_timing" in res:
        for name, v in res["eval_timing"].items():
            lines.append(
                f"logp+grad {name}: compile {v['compile_s']:.1f} s, {v['eval_ms']:.2f} ms/eval"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Command-line entry point."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="short chains (smoke run)")
    p.add_argument("--mode", default="C", help="C (default) or NUMBA")
    p.add_argument("--cores", type=int, default=1)
    p.add_argument("--draws", type=int)
    p.add_argument("--tune", type=int)
    p.add_argument("--n-check", type=int)
    p.add_argument("--compare-modes", action="store_true")
    p.add_argument("--library", action="store_true", help="only the kohpymc.GridGP run")
    a = p.parse_args(argv)
    if a.library:
        return run_library(a.quick, cores=a.cores)
    res = run(
        a.quick,
        mode=None if a.mode.upper() == "C" else a.mode.upper(),
        cores=a.cores,
        draws=a.draws,
        tune=a.tune,
        n_check=a.n_check,
        compare_modes=a.compare_modes,
    )
    print(_table(res))
    return res


if __name__ == "__main__":
    pytensor.config.on_opt_error = "raise"
    main()
