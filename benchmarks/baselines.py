"""Random-walk Metropolis baseline of ``make bench`` on numpy log posteriors.

The log posteriors of the beam formulations M0–M5 are the numpy references of
:mod:`tests.reference.beam_posteriors` (equal to ``model.compile_logp()`` of the
library's models, all constants kept); this module samples them.

:func:`random_walk_metropolis` is the paper's sampler: a Gaussian random walk whose
covariance is adapted during tuning (empirical covariance × a scalar step tuned to the
optimal acceptance) and fixed afterwards.  :func:`run_baseline` runs it for one
formulation and returns the benchmark row.  The whitened coefficients are exactly
independent standard normals *a posteriori*, so by default (``white=False``) the random
walk explores only E and the discrepancy hyperparameters (the most favourable set-up for
the baseline); ``white=True`` samples PyMC's full coordinate set.

Run ``python -m benchmarks.baselines`` (from the repository root) for the table of all
formulations.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import arviz as az
import numpy as np
import pandas as pd

import kohpymc as kp
from tests.reference.beam_posteriors import (
    DATA_PATH,
    LABELS,
    NumpyPosterior,
    beam_formulations,
    load_beam_data,
    numpy_log_posterior,
)
from tests.reference.laplace import find_starts

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


# ------------------------------------------------------------------------------- sampler
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
    data: kp.CalibrationData | None = None,
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
