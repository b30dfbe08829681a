"""surmise's calibrator on the beam, formulation M0 (no discrepancy, known noise).

surmise (https://github.com/bandframework/surmise) calibrates through an *emulator* of
the simulator and has no discrepancy term; the observation variance must be given.  It
therefore does the job of M0 with known noise: ``u = G(x; E) + ε``, ``ε ~ N(0, 0.1)``,
``E ~ Uniform(50, 300)``.

Set-up (timed as ``emulator_s``): ``n_runs`` Euler–Bernoulli runs at a Latin-hypercube
design of E over the prior, a ``PCGP`` emulator (principal components + GP in E) of the
20 outputs.  Calibration: ``calibrator(method="directbayes")`` with the known ``yvar`` and
a Uniform(50, 300) prior class (``lpdf``/``rnd``); its likelihood adds the emulator's
predictive covariance to ``diag(yvar)``.  Its sampler is surmise's ``metropolis_hastings``
(a Gaussian random walk with a fixed, diagonal step and no adaptation).  Its default step
is the sd of prior draws (≈ 72 GPa for a posterior sd ≈ 0.7 GPa: acceptance ≈ 1 %), so,
as a user would, we tune the step with pilot runs of the same calibrator: each pilot sets
``stepParam = 2.4 · sd`` of the second half of the previous pilot's draws (or divides
the step by 5 when that half has fewer than 20 moves).  Each chain is one calibrator
call with its own seed (surmise runs one chain per call); pilots + kept draws are the
sampling wall time ``wall_s``.

Run ``python -m benchmarks.surmise_baseline`` (from the repository root) for the
benchmark row.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import arviz as az
import numpy as np
from scipy import stats

import kohpymc as kp
from benchmarks.baselines import load_beam_data, summarize_E
from kohpymc.examples import beam

__all__ = ["fit_emulator", "make_uniform_prior", "run_surmise", "surmise_version"]


def surmise_version() -> str:
    """The installed surmise version."""
    from importlib.metadata import version

    return version("surmise")


def make_uniform_prior(lower: float, upper: float) -> type:
    """A surmise prior class for ``E ~ Uniform(lower, upper)`` (``lpdf`` and ``rnd``).

    Parameters
    ----------
    lower, upper : float
        Bounds of the prior.

    Returns
    -------
    type
        A class with static ``lpdf(theta) -> (n, 1)`` and ``rnd(n) -> (n, 1)`` (drawing
        with surmise's global RNG, as its samplers expect).
    """
    from surmise._RandomNumberGenerator import RandomNumberGenerator

    width = upper - lower

    class UniformPrior:
        @staticmethod
        def lpdf(theta: np.ndarray) -> np.ndarray:
            theta = np.asarray(theta, dtype=float).reshape(-1, 1)
            inside = (theta >= lower) & (theta <= upper)
            return np.where(inside, -math.log(width), -np.inf)

        @staticmethod
        def rnd(n: int) -> np.ndarray:
            rng = RandomNumberGenerator().scipy_stats_RNG
            return stats.uniform.rvs(lower, width, size=n, random_state=rng).reshape(-1, 1)

    return UniformPrior


def fit_emulator(data: kp.CalibrationData, n_runs: int = 80, seed: int = 0) -> Any:
    """A PCGP emulator of the Euler–Bernoulli outputs at the data inputs over the E prior.

    Parameters
    ----------
    data : CalibrationData
        Inputs ``x`` and ``P`` (the emulator is built at these rows).
    n_runs : int
        Simulator runs, at a Latin-hypercube design of E on its prior range.
    seed : int
        Seed of the design (and of surmise's RNG used in the fit).

    Returns
    -------
    surmise.emulation.emulator
    """
    from surmise import set_RNG
    from surmise.emulation import emulator

    prior = beam.physics_model().parameters["E"].args
    lo, hi = float(prior["lower"]), float(prior["upper"])
    set_RNG(np.random.default_rng(seed))
    design = stats.qmc.LatinHypercube(d=1, seed=seed).random(n_runs)
    theta = lo + (hi - lo) * design  # (n_runs, 1)
    X = data.matrix(["x", "P"])
    inputs = {"x": X[:, 0], "P": X[:, 1]}
    f = np.column_stack([beam.euler_bernoulli(inputs, {"E": float(e)}) for e in theta[:, 0]])
    return emulator(x=X, theta=theta, f=f, method="PCGP", args={"warnings": False})


def _calibrate(
    emu: Any,
    data: kp.CalibrationData,
    prior: type,
    *,
    samples: int,
    burn: int,
    step: float,
    theta0: float | None,
    seed: int,
) -> tuple[np.ndarray, float]:
    """One surmise directbayes/metropolis_hastings run: kept draws of E, acceptance."""
    from surmise import set_RNG
    from surmise.calibration import calibrator

    set_RNG(np.random.default_rng(seed))
    args = {
        "sampler": "metropolis_hastings",
        "nSamples": samples,
        "nBurnSamples": burn,
        "theta0": None if theta0 is None else np.array([[theta0]]),
        "stepType": "normal",
        "stepParam": np.array([step]),
        "verbose": False,
        "warnings": False,
    }
    cal = calibrator(
        emu=emu,
        y=data.y,
        x=data.matrix(["x", "P"]),
        thetaprior=prior,
        method="directbayes",
        yvar=np.full(data.n, float(data.noise_sd) ** 2),
        args=args,
    )
    draws = np.asarray(cal.info["thetarnd"], dtype=float)[:, 0]
    accept = float(np.mean(np.diff(draws) != 0.0)) if draws.size > 1 else math.nan
    return draws, accept


def run_surmise(
    data: kp.CalibrationData | None = None,
    *,
    n_runs: int = 80,
    samples: int = 10_000,
    burn: int = 500,
    pilots: int = 3,
    pilot_samples: int = 1_000,
    chains: int = 2,
    seed: int = 2026,
    return_idata: bool = False,
) -> dict[str, Any] | tuple[dict[str, Any], az.InferenceData]:
    """surmise's M0 calibration: emulator fit, pilot-tuned Metropolis, summary of E.

    Parameters
    ----------
    data : CalibrationData, optional
        Default: the beam calibration data (known noise sd).
    n_runs : int
        Simulator runs for the emulator.
    samples, burn : int
        Kept and burn-in iterations per chain.
    pilots, pilot_samples : int
        Number and length of the step-tuning pilot runs (per chain; the first uses
        surmise's default step, the sd of prior draws).
    chains : int
        Independent calibrator runs (seeds ``[seed, c]``), started from prior draws.
    seed : int
        Base seed.
    return_idata : bool
        Also return the posterior of E as InferenceData.

    Returns
    -------
    dict
        ``formulation`` ("M0"), ``sampler``, ``draws``, ``chains``, ``wall_s`` (pilots +
        burn-in + kept draws, all chains), ``cpu_s`` (its process CPU time), ``tune_s``
        (pilots), ``draw_s``,
        ``emulator_s`` (design runs + emulator fit) as ``setup_s``, ``step``,
        ``ess_bulk_E``, ``ess_tail_E``, ``ess_per_s_E``, ``rhat_E``, ``mean_E``,
        ``sd_E``, ``mcse_mean_E``, ``ess_per_cpu_s_E``, ``accept_rate``,
        ``us_per_iter``, ``surmise_version``.
    """
    data = load_beam_data() if data is None else data
    prior_args = beam.physics_model().parameters["E"].args
    lo, hi = float(prior_args["lower"]), float(prior_args["upper"])
    prior = make_uniform_prior(lo, hi)
    t0 = time.perf_counter()
    emu = fit_emulator(data, n_runs=n_runs, seed=seed)
    emulator_s = time.perf_counter() - t0
    chains_draws, accepts, steps = [], [], []
    tune_s = draw_s = 0.0
    cpu0 = time.process_time()
    for c in range(chains):
        child = int(np.random.SeedSequence([seed, c]).generate_state(1)[0])
        t1 = time.perf_counter()
        step, theta0 = (hi - lo) / math.sqrt(12.0), None  # surmise's default: prior sd
        for p in range(pilots):
            pilot, _ = _calibrate(
                emu,
                data,
                prior,
                samples=pilot_samples,
                burn=0,
                step=step,
                theta0=theta0,
                seed=child + 1 + p,
            )
            half = pilot[pilot_samples // 2 :]
            if np.count_nonzero(np.diff(half)) >= 20:
                step = 2.4 * float(np.std(half))
            else:  # too few moves to estimate the spread: shrink the step
                step /= 5.0
            theta0 = float(pilot[-1])
        t2 = time.perf_counter()
        # the kept run restarts from a prior draw (theta0=None): chains stay independent
        draws, accept = _calibrate(
            emu, data, prior, samples=samples, burn=burn, step=step, theta0=None, seed=child
        )
        t3 = time.perf_counter()
        tune_s += t2 - t1
        draw_s += t3 - t2
        chains_draws.append(draws)
        accepts.append(accept)
        steps.append(step)
    cpu_s = time.process_time() - cpu0
    idata = az.from_dict(posterior={"E": np.vstack(chains_draws)})
    wall_s = tune_s + draw_s
    summary = summarize_E(idata, wall_s)
    row: dict[str, Any] = {
        "formulation": "M0",
        "sampler": "surmise directbayes+MH",
        "dim": 1,
        "draws": samples,
        "tune": burn,
        "chains": chains,
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        "tune_s": tune_s,
        "draw_s": draw_s,
        "setup_s": emulator_s,
        "emulator_runs": n_runs,
        "step": float(np.mean(steps)),
        **summary,
        "ess_per_cpu_s_E": summary["ess_bulk_E"] / cpu_s,
        "accept_rate": float(np.mean(accepts)),
        "us_per_iter": 1e6 * wall_s / (chains * (samples + burn + pilots * pilot_samples)),
        "surmise_version": surmise_version(),
    }
    return (row, idata) if return_idata else row


def _main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="surmise calibrator baseline, beam M0.")
    parser.add_argument("--runs", type=int, default=80, help="simulator runs for the emulator")
    parser.add_argument("--samples", type=int, default=10_000)
    parser.add_argument("--burn", type=int, default=500)
    parser.add_argument("--chains", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--json", type=Path, help="write the row as JSON here")
    args = parser.parse_args(argv)
    row = run_surmise(
        n_runs=args.runs,
        samples=args.samples,
        burn=args.burn,
        chains=args.chains,
        seed=args.seed,
    )
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}))
    if args.json:
        args.json.write_text(json.dumps(row, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
