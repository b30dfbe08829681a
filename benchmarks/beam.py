"""kohpymc on the beam problem (n = 20): one benchmark row per formulation and sampler.

Each row is one :func:`kohpymc.calibrate` call on the paper's beam calibration data
(load 2.5, known noise) — the library as a user runs it, including the identifiability
check and the pointwise log-likelihood — with

* ``pymc``: PyMC's NUTS, the numpy physics function with its analytic Jacobian (what
  ``kohpymc study`` runs), chains in parallel processes (``cores=2``);
* ``pymc-numba``: PyMC's NUTS with the physics as a PyTensor expression and
  ``mode="NUMBA"`` (the log density and gradient compiled by numba);
* ``nutpie``: nutpie's NUTS (Rust) with the physics as a PyTensor expression, so the
  whole log density compiles to one numba function.

``sampling_s`` is the sampler's own time (tuning + draws, ``posterior.attrs
["sampling_time"]``), ``compile_s`` the rest of the call (model build, compilation,
checks, log-likelihood).  ESS/s uses ``sampling_s``, as the random-walk baseline does.
"""

from __future__ import annotations

import time
import warnings
from typing import Any, Literal

import arviz as az
import numpy as np

import kohpymc as kp
from benchmarks.baselines import beam_formulations, load_beam_data
from kohpymc.examples import beam

__all__ = ["run_kohpymc", "run_study"]


def _summary(idata: az.InferenceData, sampling_s: float) -> dict[str, float]:
    ess_bulk = float(az.ess(idata, var_names=["E"], method="bulk")["E"])
    return {
        "ess_bulk_E": ess_bulk,
        "ess_tail_E": float(az.ess(idata, var_names=["E"], method="tail")["E"]),
        "ess_per_s_E": ess_bulk / sampling_s,
        "rhat_E": float(az.rhat(idata, var_names=["E"])["E"]),
        "rhat_max": float(
            max(
                float(az.rhat(idata, var_names=[v])[v].max())
                for v in idata.posterior.data_vars
                if not v.endswith("__")
            )
        ),
        "mean_E": float(idata.posterior["E"].mean()),
        "sd_E": float(idata.posterior["E"].std()),
    }


def run_kohpymc(
    label: str,
    sampler: Literal["pymc", "pymc-numba", "nutpie"] = "pymc",
    *,
    draws: int = 2000,
    tune: int = 1000,
    chains: int = 2,
    seed: int = 2026,
) -> dict[str, Any]:
    """Calibrate one beam formulation with kohpymc and return the benchmark row.

    Parameters
    ----------
    label : str
        ``"M0"`` ... ``"M5"`` (:func:`benchmarks.baselines.beam_formulations`).
    sampler : {"pymc", "pymc-numba", "nutpie"}
        NUTS implementation (see the module docstring).
    draws, tune, chains, seed :
        Passed to :func:`kohpymc.calibrate`.

    Returns
    -------
    dict
        ``formulation, sampler, draws, tune, chains, wall_s, compile_s, sampling_s,
        ess_bulk_E, ess_tail_E, ess_per_s_E, rhat_E, rhat_max, divergences, mean_E, sd_E,
        steps_per_draw``.
    """
    data = load_beam_data()
    discrepancy = beam_formulations()[label]
    physics = beam.physics_model(backend="numpy" if sampler == "pymc" else "pytensor")
    extra = {"mode": "NUMBA"} if sampler == "pymc-numba" else {}
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        idata = kp.calibrate(
            physics,
            data,
            discrepancy,
            draws=draws,
            tune=tune,
            chains=chains,
            cores=chains,
            random_seed=seed,
            nuts_sampler="nutpie" if sampler == "nutpie" else "pymc",
            warn=False,
            **extra,
        ).idata
    wall = time.perf_counter() - start
    sampling = float(idata.posterior.attrs["sampling_time"])
    stats = idata.sample_stats
    steps = stats["n_steps"] if "n_steps" in stats else stats["tree_size"]
    return {
        "formulation": label,
        "sampler": f"kohpymc/{sampler}",
        "draws": draws,
        "tune": tune,
        "chains": chains,
        "wall_s": wall,
        "compile_s": wall - sampling,
        "sampling_s": sampling,
        **_summary(idata, sampling),
        "divergences": int(stats["diverging"].sum()),
        "steps_per_draw": float(np.mean(steps)),
    }


def run_study(
    *,
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 2,
    seed: int = 2026,
    numba: bool = False,
    workers: int = 1,
) -> dict[str, Any]:
    """The whole beam study (M0–M4, validation, combination) timed end to end.

    Runs :func:`kohpymc.run_study` on the shipped beam study (``beam_study.toml``'s
    data and formulations) with chains in parallel, writing nothing.  ``numba=True``
    swaps in the same physics as a PyTensor expression and samples with
    ``mode="NUMBA"`` (the shipped file has a numpy function and PyTensor's C backend).
    ``workers=2`` calibrates two formulations at a time, each with its chains in
    sequence (``cores=1``), instead of one formulation with its chains in parallel.

    Returns
    -------
    dict
        ``wall_s``, per-formulation calibration seconds, ``rhat_max`` over the
        formulations' physics parameters, ``divergences`` and μ_r per formulation.
    """
    from pathlib import Path

    study = kp.load_study(Path(beam.__file__).with_name("beam_study.toml"))
    physics = beam.physics_model(backend="pytensor") if numba else study.physics
    extra = {"mode": "NUMBA"} if numba else {}
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = kp.run_study(
            physics,
            study.calibration,
            study.validation,
            study.formulations,
            tolerance=study.tolerance,
            draws=draws,
            tune=tune,
            chains=chains,
            cores=1 if workers > 1 else chains,
            workers=workers,
            random_seed=seed,
            progress=None,
            **extra,
        )
    wall = time.perf_counter() - start
    rhat, ess, divergences = [], [], 0
    for idata in result.results.values():
        rhat.append(float(az.rhat(idata, var_names=["E"])["E"]))
        ess.append(float(az.ess(idata, var_names=["E"])["E"]))
        divergences += int(idata.sample_stats["diverging"].sum())
    return {
        "variant": ("PyTensor physics, NUMBA mode" if numba else "shipped file (numpy physics, C)")
        + (f", {workers} formulations at a time" if workers > 1 else ""),
        "draws": draws,
        "tune": tune,
        "chains": chains,
        "wall_s": wall,
        "formulations": list(result.results),
        "calibration_s": {k: round(float(v), 2) for k, v in result.wall_time_s.items()},
        "rhat_max_E": max(rhat),
        "ess_bulk_min_E": min(ess),
        "divergences": divergences,
        "mu_r": {k: round(float(v), 3) for k, v in result.table["mu_r"].dropna().items()},
    }
