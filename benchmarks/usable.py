"""Time to a usable posterior: wall seconds until every free parameter has ESS and r̂ in range.

For each problem × formulation × sampler this measures the wall time, *including* model
build, compilation and set-up (each attempt is one fresh :func:`kohpymc.calibrate`
call), until every free parameter of the model has ``ESS_bulk >= 1000`` and
``r_hat <= 1.01``.  "Free parameters" are the model's free random variables as they
appear in the posterior: the physics parameters, ``sigma_obs`` when the noise is
calibrated, the discrepancy hyper-parameters and the whitened discrepancy-mean
coefficients (``*_white``); every element of a vector counts.

Procedure (:func:`until_usable`): sample with ``draws`` = 1000 per chain (4 chains, 1000
tuning steps); if the criterion fails, double the draws and start again from scratch
(a new ``calibrate`` call, seed + attempt number), up to ``max_draws`` (16,000) or until
the next attempt (estimated as twice the last) would pass ``time_limit`` seconds in
total.  ``wall_s`` is the time of *all* attempts.  When the target is not reached the
row reports the attempt with the largest minimum ESS, ``reached`` is False and
``wall_s`` is a lower bound.  ``divergences`` are those of the reported attempt.

Samplers

* ``kohpymc``: the library's default (``sampler=None``: nutpie in coordinates whitened
  at the posterior mode).  If the call raises, the row records the error (``note``) and,
  with ``retry_single_core=True``, a second row ``kohpymc(cores=1)`` repeats the cell
  with the chains in one thread.
* ``pymc-nuts``: ``sampler="pymc", reparameterize=False``, PyMC's NUTS in PyMC's own
  coordinates (the library's previous default).
* ``rwm``: the random-walk Metropolis baseline of :mod:`benchmarks.baselines` (beam
  M0–M5, known noise only: its numpy posteriors exist for those).  Its time is
  extrapolated from one run, as the benchmark of :mod:`benchmarks.run` does: set-up
  (MAP, Laplace covariance, starts) + tuning + kept-draw seconds × 1000 / (min ESS),
  from a run whose own min ESS is at least 1000 and whose r̂ is at most 1.01 (its draws
  are doubled, from 20,000 per chain, until that holds; earlier runs are not counted).
  It samples E and the discrepancy hyper-parameters only (the whitened coefficients
  are exactly independent N(0, 1) a posteriori), the most favourable set-up for it.
* ``surmise``: :mod:`benchmarks.surmise_baseline` for beam M0 (known noise; ESS of E),
  extrapolated like ``rwm``; skipped when surmise is not installed.

Problems

* ``beam``: the paper's beam data (n = 20, load 2.5, known noise), formulations M0–M5
  of :func:`benchmarks.baselines.beam_formulations`, numpy physics with its Jacobian;
* ``beam-2load``: :func:`kohpymc.examples.beam.generate_data` at loads 2.5 and 3.5
  (n = 40, seed 2026) with the noise sd *not* recorded, so ``sigma_obs`` is calibrated;
  the same formulations M0–M5;
* ``linear``, ``arrhenius``, ``collinear``, ``multiplicative``:
  :func:`kohpymc.examples.hard_posteriors.all_problems` (unknown noise) under M0
  (NoDiscrepancy) and M1 (ConstantBias).  ``ratio_to_linear`` is ``wall_s`` over that of
  ``linear`` under the same formulation and sampler in the same run.

* ``dielectric``: the paper's Section 6.2 stand-in (:mod:`kohpymc.examples.dielectric`,
  240 calibration rows, seven physics parameters in natural units, noise sd known) under
  its M0–M5, the chains started at ``least_squares_fit`` as the slow test does
  (:func:`dielectric_cases`).  Its slow formulations end at ``attempt_timeout`` (600 s)
  as "not reached"; this problem adds up to ~2 h to the run.

Run ``python -m benchmarks.usable`` (or ``python -m benchmarks.run --only usable``);
``--problems``, ``--samplers``, ``--chains`` ... select a reduced run.  Tables go to
``<out>/usable.md`` and ``usable.csv``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import multiprocessing
import os
import platform
import re
import signal
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import arviz as az  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

import kohpymc as kp  # noqa: E402

__all__ = [
    "COLUMNS",
    "PROBLEMS",
    "SAMPLERS",
    "Case",
    "cases",
    "diagnostics",
    "is_reached",
    "main",
    "ratio_to_linear",
    "until_usable",
    "usable_table",
]

#: the table's columns; ``worst`` (the parameter with the smallest ESS) and ``note``
#: (errors, fall-backs, why the doubling stopped) follow in the CSV and markdown
COLUMNS = [
    "problem",
    "formulation",
    "sampler",
    "wall_s",
    "attempts",
    "draws",
    "min_ess_bulk",
    "max_rhat",
    "divergences",
    "reached",
    "ratio_to_linear",
]
EXTRA = ["worst", "note"]
PROBLEMS = (
    "beam",
    "beam-2load",
    "linear",
    "arrhenius",
    "collinear",
    "multiplicative",
    "dielectric",
)
HARD = ("linear", "arrhenius", "collinear", "multiplicative")
SAMPLERS = ("kohpymc", "pymc-nuts", "rwm", "surmise")
BEAM_LOADS = (2.5, 3.5)
BEAM_SEED = 2026


# ------------------------------------------------------------------------------ criterion
def is_reached(min_ess: float, max_rhat: float, target_ess: float, max_rhat_ok: float) -> bool:
    """Whether ``min_ess >= target_ess`` and ``max_rhat <= max_rhat_ok`` (NaN fails).

    Examples
    --------
    >>> is_reached(1200.0, 1.004, 1000, 1.01), is_reached(900.0, 1.0, 1000, 1.01)
    (True, False)
    >>> is_reached(float("nan"), 1.0, 1000, 1.01)
    False
    """
    return bool(
        math.isfinite(min_ess)
        and math.isfinite(max_rhat)
        and min_ess >= target_ess
        and max_rhat <= max_rhat_ok
    )


def diagnostics(idata: az.InferenceData, var_names: Sequence[str]) -> dict[str, Any]:
    """Minimum bulk ESS, maximum r̂ over every element of ``var_names``; divergences.

    Parameters
    ----------
    idata : arviz.InferenceData
        With a ``posterior`` (and optionally ``sample_stats.diverging``).
    var_names : sequence of str
        Posterior variables to check.

    Returns
    -------
    dict
        ``min_ess_bulk``, ``max_rhat``, ``worst`` (variable of the smallest ESS, with
        its index for vectors) and ``divergences``.
    """
    ess = az.ess(idata, var_names=list(var_names), method="bulk")
    rhat = az.rhat(idata, var_names=list(var_names))
    min_ess, worst, max_rhat = math.inf, "", -math.inf
    for name in var_names:
        e = np.asarray(ess[name], dtype=float).ravel()
        r = np.asarray(rhat[name], dtype=float).ravel()
        if e.size == 0:
            continue
        i = int(np.nanargmin(e)) if np.any(np.isfinite(e)) else 0
        if not np.isfinite(e[i]) or e[i] < min_ess:
            min_ess = float(e[i])
            worst = name if e.size == 1 else f"{name}[{i}]"
        max_rhat = max(max_rhat, float(np.max(r))) if np.all(np.isfinite(r)) else math.nan
    stats = idata.get("sample_stats")
    divergences = int(stats["diverging"].sum()) if stats is not None and "diverging" in stats else 0
    return {
        "min_ess_bulk": min_ess if math.isfinite(min_ess) else math.nan,
        "max_rhat": max_rhat,
        "worst": worst,
        "divergences": divergences,
    }


def until_usable(
    attempt: Callable[[int, int], dict[str, Any]],
    *,
    draws: int = 1000,
    max_draws: int = 16_000,
    time_limit: float = 300.0,
    target_ess: float = 1000.0,
    max_rhat: float = 1.01,
) -> dict[str, Any]:
    """Double the draws until ``attempt`` meets the criterion; the total wall time.

    Parameters
    ----------
    attempt : callable
        ``attempt(draws, index) -> dict`` with at least ``min_ess_bulk`` and
        ``max_rhat`` (optionally ``divergences``, ``worst``, ``note``); ``index`` counts
        attempts from 0 (use it to vary the seed).  Its wall time is measured here.
    draws : int
        Draws per chain of the first attempt.
    max_draws : int
        No attempt with more draws per chain.
    time_limit : float
        No new attempt when the total so far plus twice the last attempt's seconds
        would exceed it.
    target_ess, max_rhat :
        The criterion (:func:`is_reached`).

    Returns
    -------
    dict
        ``wall_s`` (all attempts), ``attempts``, ``draws`` (of the reported attempt),
        ``min_ess_bulk``, ``max_rhat``, ``divergences``, ``worst``, ``reached``, ``note``.
        The reported attempt is the one that met the criterion, else the one with the
        largest minimum ESS.  An exception in ``attempt`` (including a Rust panic from
        nutpie, which is not an ``Exception``) ends the loop with its text in ``note``.

    Examples
    --------
    >>> fake = lambda d, i: {"min_ess_bulk": d / 3, "max_rhat": 1.0}
    >>> row = until_usable(fake, draws=1000, max_draws=16000)
    >>> row["attempts"], row["draws"], row["reached"]
    (3, 4000, True)
    """
    total, index, best, notes = 0.0, 0, None, []
    d = int(draws)
    while True:
        start = time.perf_counter()
        try:
            result = dict(attempt(d, index))
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as err:  # noqa: BLE001 - pyo3 PanicException is BaseException
            total += time.perf_counter() - start
            index += 1
            if isinstance(err, AttemptTimeout):
                notes.append(str(err))
            else:
                detail = str(err) if isinstance(err, AttemptFailed) else describe_error(err)
                notes.append(f"error at {d} draws: {detail}")
            break
        elapsed = time.perf_counter() - start
        total += elapsed
        index += 1
        result["draws"] = d
        result["reached"] = is_reached(
            float(result["min_ess_bulk"]), float(result["max_rhat"]), target_ess, max_rhat
        )
        if result.get("note"):
            notes.append(str(result["note"]))
        ess = float(result["min_ess_bulk"])
        best_ess = -math.inf if best is None else float(best["min_ess_bulk"])
        if best is None or result["reached"] or (math.isfinite(ess) and ess > best_ess):
            best = result
        if result["reached"]:
            break
        if 2 * d > max_draws:
            notes.append(f"not reached by {d} draws (cap {max_draws})")
            break
        if total + 2.0 * elapsed > time_limit:
            notes.append(
                f"not reached; stopped at {total:.0f} s: the next attempt (~2 x {elapsed:.0f} s)"
                f" would pass the {time_limit:.0f} s limit"
            )
            break
        d *= 2
    row: dict[str, Any] = {
        "wall_s": total,
        "attempts": index,
        "draws": d,
        "min_ess_bulk": math.nan,
        "max_rhat": math.nan,
        "divergences": math.nan,
        "worst": "",
        "reached": False,
    }
    if best is not None:
        row.update({k: best.get(k, row.get(k)) for k in (*row, "worst")})
        row["wall_s"], row["attempts"] = total, index
    row["note"] = "; ".join(dict.fromkeys(notes))  # unique, in order
    return row


# ---------------------------------------------------------------------------------- cases
@dataclass(frozen=True)
class Case:
    """One problem under one formulation.

    Attributes
    ----------
    problem, formulation : str
        Row labels.
    physics : kohpymc.PhysicsModel
    data : kohpymc.CalibrationData
    discrepancy : kohpymc discrepancy formulation
    rwm : bool
        The random-walk baseline has a numpy posterior for this case.
    """

    problem: str
    formulation: str
    physics: Any
    data: Any
    discrepancy: Any
    rwm: bool = False
    extra: dict[str, Any] = field(default_factory=dict)


def beam_two_load_data(seed: int = BEAM_SEED) -> kp.CalibrationData:
    """Beam data at loads 2.5 and 3.5 (n = 40) with the noise sd left unknown.

    Examples
    --------
    >>> data = beam_two_load_data()
    >>> data.n, data.noise_sd
    (40, None)
    """
    from kohpymc.examples import beam

    known = beam.generate_data(BEAM_LOADS, seed=seed)
    return kp.CalibrationData(
        pd.DataFrame({k: np.asarray(v) for k, v in known.inputs.items()}),
        known.y,
        noise_sd=None,
        output_name=known.output_name,
    )


def cases(
    problems: Sequence[str] = PROBLEMS,
    formulations: Sequence[str] | None = None,
    seed: int = 0,
) -> list[Case]:
    """The benchmark's cases, in table order.

    Parameters
    ----------
    problems : sequence of str
        Subset of :data:`PROBLEMS`.
    formulations : sequence of str, optional
        Keep only these labels (default: M0–M5 for the beam problems and the dielectric
        stand-in, M0–M1 for the hard ones).
    seed : int
        Seed of the hard problems' noise.
    """
    from benchmarks.baselines import beam_formulations, load_beam_data
    from kohpymc.discrepancy import ConstantBias, NoDiscrepancy
    from kohpymc.examples import beam
    from kohpymc.examples.hard_posteriors import all_problems

    unknown = set(problems) - set(PROBLEMS)
    if unknown:
        raise ValueError(f"unknown problems {sorted(unknown)}; choose from {PROBLEMS}")
    keep = (lambda label: True) if formulations is None else set(formulations).__contains__
    out: list[Case] = []
    for name in problems:
        if name in ("beam", "beam-2load"):
            data = load_beam_data() if name == "beam" else beam_two_load_data()
            for label, disc in beam_formulations().items():
                if keep(label):
                    out.append(
                        Case(name, label, beam.physics_model(), data, disc, rwm=name == "beam")
                    )
        elif name == "dielectric":
            out.extend(c for c in dielectric_cases() if keep(c.formulation))
        else:
            problem = all_problems(seed)[name]
            for label, disc in (("M0", NoDiscrepancy()), ("M1", ConstantBias())):
                if keep(label):
                    out.append(Case(name, label, problem.physics, problem.data, disc))
    return out


def dielectric_cases() -> list[Case]:
    """The paper's Section 6.2 stand-in, M0–M5, as the slow test calls it.

    Data ``generate_data(seed=2026)``, calibration half; the chains start at
    ``least_squares_fit`` (which does not use the truth), passed as ``initvals``.
    """
    from kohpymc.examples import dielectric

    cal, _ = dielectric.split_calibration_validation(dielectric.generate_data(seed=2026))
    start = {"initvals": dielectric.least_squares_fit(cal)}
    return [
        Case("dielectric", label, dielectric.physics_model(), cal, disc, extra=start)
        for label, disc in dielectric.formulations().items()
    ]


# ---------------------------------------------------------------------- isolated attempts
class AttemptFailed(RuntimeError):
    """An isolated attempt raised (the message is its text)."""


class AttemptTimeout(AttemptFailed):
    """An isolated attempt ran out of time."""


_LOGP_ERROR = re.compile(r"type: <class '([\w.]+)'>, value: \w+\((['\"])(.*?)(?:\\n|(?<!\\)\2\))")


def describe_error(err: BaseException, limit: int = 200) -> str:
    r"""One line on ``err``; for a nutpie panic, the log-density error that caused it.

    A failing log density makes nutpie's Rust worker panic; what reaches Python is often
    a second panic ("Poisond sampler state mutex") whose ``__context__`` chain holds the
    first, with the Python error (escaped, as in a repr) in its text.

    Examples
    --------
    >>> try:
    ...     try:
    ...         raise RuntimeError("Logp function returned error: PyError(PyErr { type: <class "
    ...                            "'ValueError'>, value: ValueError('bad \\'x\\'\\nmore') })")
    ...     except RuntimeError:
    ...         raise RuntimeError("Poisond sampler state mutex")
    ... except RuntimeError as exc:
    ...     print(describe_error(exc))
    RuntimeError: Poisond sampler state mutex (log density raised ValueError: bad 'x')
    """
    lines = str(err).splitlines()
    text = f"{type(err).__name__}: {lines[0] if lines else ''}"
    seen, link = set(), err
    while link is not None and id(link) not in seen:
        seen.add(id(link))
        match = _LOGP_ERROR.search(str(link))
        if match:
            message = match.group(3).replace("\\'", "'").replace('\\"', '"')
            cause = f"{match.group(1).rsplit('.', 1)[-1]}: {message}"
            text = f"{text.split(': called `Result')[0]} (log density raised {cause})"
            break
        link = link.__context__ or link.__cause__
    return text[:limit]


def isolated(
    attempt: Callable[[int, int], dict[str, Any]], timeout: float | None
) -> Callable[[int, int], dict[str, Any]]:
    """``attempt`` run in a forked child process, killed after ``timeout`` seconds.

    The child leads its own process group, so a timeout kills it together with the
    sampler's worker processes (PyMC's chains).  A Rust panic in nutpie or any other
    exception in the child comes back as :class:`AttemptFailed`.  ``timeout=None``
    returns ``attempt`` itself (run in this process, no time limit).
    """
    if timeout is None:
        return attempt

    def run(draws: int, index: int) -> dict[str, Any]:
        ctx = multiprocessing.get_context("fork")
        receive, send = ctx.Pipe(duplex=False)

        def target() -> None:
            os.setpgid(0, 0)
            try:
                message: tuple[str, Any] = ("ok", attempt(draws, index))
            except BaseException as err:  # noqa: BLE001 - reported to the parent
                message = ("error", describe_error(err))
            send.send(message)
            send.close()
            os._exit(0)

        proc = ctx.Process(target=target)
        proc.start()
        send.close()
        try:
            status, payload = receive.recv() if receive.poll(timeout) else ("timeout", None)
        except EOFError:  # the child died without a word (e.g. a segfault)
            status, payload = "error", f"child exited with code {proc.exitcode}"
        if status == "timeout":
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        proc.join()
        receive.close()
        if status == "ok":
            return payload
        if status == "timeout":
            raise AttemptTimeout(f"attempt at {draws} draws timed out after {timeout:.0f} s")
        raise AttemptFailed(payload)

    return run


# ------------------------------------------------------------------------------- samplers
def _kohpymc_attempt(
    case: Case,
    *,
    sampler: str | None,
    reparameterize: bool,
    tune: int,
    chains: int,
    seed: int,
    cores: int | None = None,
) -> Callable[[int, int], dict[str, Any]]:
    def attempt(draws: int, index: int) -> dict[str, Any]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal = kp.calibrate(
                case.physics,
                case.data,
                case.discrepancy,
                sampler=sampler,
                reparameterize=reparameterize,
                draws=draws,
                tune=tune,
                chains=chains,
                cores=cores,
                random_seed=seed + index,
                warn=False,
                **case.extra,
            )
        idata = cal.idata
        names = [rv.name for rv in cal.built.model.free_RVs if rv.name in idata.posterior]
        out = diagnostics(idata, names)
        info = json.loads(idata.attrs.get("sampling", "{}"))
        requested = "nutpie" if sampler is None else sampler
        if info.get("sampler") and info["sampler"] != requested:
            out["note"] = f"ran {info['sampler']}: {info.get('fallback_reason', '')}"[:160]
        return out

    return attempt


def _extrapolated(
    run: Callable[[int, int], dict[str, Any]],
    *,
    draws: int,
    max_draws: int,
    time_limit: float,
    target_ess: float,
    max_rhat: float,
) -> dict[str, Any]:
    """A baseline timed by extrapolation: run with doubling draws until the run itself
    meets the criterion, then ``setup + tune + draw_s * target / min_ess``."""
    spent, runs, d, last = 0.0, 0, int(draws), None
    while True:
        start = time.perf_counter()
        last = run(d, runs)
        runs += 1
        spent += time.perf_counter() - start
        last["reached"] = is_reached(last["min_ess_bulk"], last["max_rhat"], target_ess, max_rhat)
        if last["reached"] or 2 * d > max_draws or spent > time_limit:
            break
        d *= 2
    scale = target_ess / last["min_ess_bulk"] if last["reached"] else 1.0
    wall = last["setup_s"] + last["tune_s"] + last["draw_s"] * scale
    note = (
        f"extrapolated from {d} draws/chain ({last['draw_s']:.1f} s kept draws)"
        if last["reached"]
        else f"not reached by {d} draws/chain"
    )
    return {
        "wall_s": wall,
        "attempts": runs,
        "draws": d,
        "min_ess_bulk": last["min_ess_bulk"],
        "max_rhat": last["max_rhat"],
        "divergences": 0,
        "worst": last.get("worst", ""),
        "reached": last["reached"],
        "note": note,
    }


def _rwm_run(case: Case, *, chains: int, seed: int) -> Callable[[int, int], dict[str, Any]]:
    from benchmarks.baselines import run_baseline

    def run(draws: int, index: int) -> dict[str, Any]:
        row, res = run_baseline(
            case.formulation,
            draws=draws,
            tune=20_000,
            chains=chains,
            seed=seed + index,
            data=case.data,
            return_result=True,
        )
        out = diagnostics(res.idata, list(res.idata.posterior.data_vars))
        out.update(setup_s=row["setup_s"], tune_s=row["tune_s"], draw_s=row["draw_s"])
        return out

    return run


def _surmise_run(chains: int, seed: int) -> Callable[[int, int], dict[str, Any]]:
    from benchmarks.surmise_baseline import run_surmise

    def run(draws: int, index: int) -> dict[str, Any]:
        row, idata = run_surmise(samples=draws, chains=chains, seed=seed + index, return_idata=True)
        out = diagnostics(idata, ["E"])
        out.update(setup_s=row["setup_s"], tune_s=row["tune_s"], draw_s=row["draw_s"])
        return out

    return run


def surmise_available() -> bool:
    """Whether ``surmise`` can be imported."""
    return importlib.util.find_spec("surmise") is not None


# ---------------------------------------------------------------------------------- table
def usable_table(
    problems: Sequence[str] = PROBLEMS,
    samplers: Sequence[str] = SAMPLERS,
    *,
    formulations: Sequence[str] | None = None,
    target_ess: float = 1000.0,
    max_rhat: float = 1.01,
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 4,
    max_draws: int = 16_000,
    time_limit: float = 300.0,
    attempt_timeout: float | None = 600.0,
    rwm_draws: int = 20_000,
    rwm_max_draws: int = 320_000,
    seed: int = 2026,
    retry_single_core: bool = True,
    progress: Callable[[str], None] | None = print,
) -> pd.DataFrame:
    """Time to a usable posterior for every case and sampler (see the module docstring).

    Parameters
    ----------
    problems, samplers : sequence of str
        Subsets of :data:`PROBLEMS` and :data:`SAMPLERS`.
    formulations : sequence of str, optional
        Keep only these formulation labels.
    target_ess, max_rhat :
        The criterion.
    draws, tune, chains, max_draws, time_limit :
        The NUTS doubling procedure (:func:`until_usable`).
    attempt_timeout : float, optional
        Run each kohpymc attempt in a child process killed after this many seconds
        (:func:`isolated`; the row is then "not reached"); None: in this process.
    rwm_draws, rwm_max_draws :
        First and largest kept draws per chain of the random-walk baseline (and of
        surmise).
    seed : int
        Sampler seed (attempt ``i`` uses ``seed + i``).
    retry_single_core : bool
        When the default kohpymc call raises, repeat the cell with ``cores=1``.
    progress : callable, optional
        Called with one line per finished row.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`COLUMNS` then ``worst``, ``note``.
    """
    unknown = set(samplers) - set(SAMPLERS)
    if unknown:
        raise ValueError(f"unknown samplers {sorted(unknown)}; choose from {SAMPLERS}")
    nuts = dict(
        draws=draws,
        max_draws=max_draws,
        time_limit=time_limit,
        target_ess=target_ess,
        max_rhat=max_rhat,
    )
    extrap = dict(nuts, draws=rwm_draws, max_draws=rwm_max_draws)
    rows: list[dict[str, Any]] = []

    def add(case: Case, sampler: str, row: dict[str, Any]) -> None:
        row = {"problem": case.problem, "formulation": case.formulation, "sampler": sampler, **row}
        rows.append(row)
        if progress is not None:
            progress(
                f"  {case.problem:<14} {case.formulation} {sampler:<16} "
                f"{row['wall_s']:7.1f} s  attempts {row['attempts']}  draws {row['draws']}  "
                f"min ESS {row['min_ess_bulk']:.0f}  r_hat {row['max_rhat']:.3f}  "
                f"reached {row['reached']}" + (f"  ({row['note']})" if row["note"] else "")
            )

    surmise_ok = "surmise" in samplers and surmise_available()
    if "surmise" in samplers and not surmise_ok and progress is not None:
        progress("  surmise not installed: its row is skipped")
    for case in cases(problems, formulations):
        if "kohpymc" in samplers:
            kw = dict(sampler=None, reparameterize=True, tune=tune, chains=chains, seed=seed)
            row = until_usable(isolated(_kohpymc_attempt(case, **kw), attempt_timeout), **nuts)
            add(case, "kohpymc", row)
            if retry_single_core and "error at" in row["note"]:
                single = isolated(_kohpymc_attempt(case, **kw, cores=1), attempt_timeout)
                add(case, "kohpymc(cores=1)", until_usable(single, **nuts))
        if "pymc-nuts" in samplers:
            kw = dict(sampler="pymc", reparameterize=False, tune=tune, chains=chains, seed=seed)
            attempt = isolated(_kohpymc_attempt(case, **kw), attempt_timeout)
            add(case, "pymc-nuts", until_usable(attempt, **nuts))
        if "rwm" in samplers and case.rwm:
            add(case, "rwm", _extrapolated(_rwm_run(case, chains=chains, seed=seed), **extrap))
        if surmise_ok and case.problem == "beam" and case.formulation == "M0":
            add(case, "surmise", _extrapolated(_surmise_run(chains, seed), **extrap))
    frame = pd.DataFrame(rows, columns=[*COLUMNS, *EXTRA])
    frame["reached"] = frame["reached"].astype(bool)
    frame["ratio_to_linear"] = ratio_to_linear(frame)
    return frame


def ratio_to_linear(frame: pd.DataFrame) -> pd.Series:
    """``wall_s`` over the linear problem's under the same formulation and sampler.

    NaN unless the linear row reached the target, and for rows that ended in an error
    (their ``wall_s`` is the time to the failure).  A row that was not reached for want
    of draws or time has a lower bound.

    Examples
    --------
    >>> frame = pd.DataFrame({"problem": ["linear", "arrhenius", "beam"],
    ...     "formulation": ["M0"] * 3, "sampler": ["kohpymc"] * 3,
    ...     "wall_s": [10.0, 25.0, 5.0], "reached": [True, False, True],
    ...     "note": ["", "attempt at 1000 draws timed out after 180 s", ""]})
    >>> ratio_to_linear(frame).tolist()
    [1.0, 2.5, nan]
    """
    linear = frame[(frame["problem"] == "linear") & frame["reached"].astype(bool)]
    reference = linear.set_index(["formulation", "sampler"])["wall_s"]
    ratio = pd.Series(np.nan, index=frame.index, dtype=float)
    notes = frame["note"].fillna("").astype(str)
    for i in frame.index[frame["problem"].isin(HARD)]:
        key = (frame.at[i, "formulation"], frame.at[i, "sampler"])
        if key in reference.index and "error at" not in notes[i]:
            ratio[i] = frame.at[i, "wall_s"] / float(reference[key])
    return ratio


def _display(frame: pd.DataFrame) -> pd.DataFrame:
    """The table as text cells: seconds to 3 digits, ESS whole, r̂ to 3 decimals."""
    out = frame.copy().astype(object)
    for col, fmt in (("wall_s", "{:.3g}"), ("ratio_to_linear", "{:.3g}")):
        out[col] = [fmt.format(v) if pd.notna(v) else "" for v in frame[col]]
    out["min_ess_bulk"] = [f"{v:.0f}" if pd.notna(v) else "" for v in frame["min_ess_bulk"]]
    out["max_rhat"] = [f"{v:.3f}" if pd.notna(v) else "" for v in frame["max_rhat"]]
    out["divergences"] = [f"{v:.0f}" if pd.notna(v) else "" for v in frame["divergences"]]
    out["note"] = frame["note"].fillna("").astype(str)
    out["worst"] = frame["worst"].fillna("").astype(str)
    return out


def write_tables(frame: pd.DataFrame, out: Path, header: str) -> str:
    """Write ``usable.csv`` and ``usable.md`` into ``out``; return the markdown table."""
    from benchmarks.run import markdown_table

    out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out / "usable.csv", index=False)
    md = markdown_table(_display(frame).set_index("problem"))
    (out / "usable.md").write_text(f"{header}\n\n{md}\n")
    return md


def settings_header(args: argparse.Namespace, machine: str) -> str:
    """The first paragraph of ``usable.md``: machine, criterion and settings."""
    return (
        f"Time to a usable posterior, {machine}\n\n"
        f"Criterion: every free parameter ESS_bulk >= {args.target_ess:g} and "
        f"r_hat <= {args.max_rhat:g}. NUTS: {args.chains} chains, tune {args.tune}, draws "
        f"{args.draws} doubled up to {args.max_draws} (no new attempt past "
        f"{args.time_limit:g} s per row; an attempt is killed after "
        f"{args.attempt_timeout:g} s); wall_s counts every attempt including compilation "
        "and set-up. rwm/surmise: set-up + tuning + kept-draw time scaled to the target "
        "ESS. Rows with reached = False: wall_s is a lower bound. Problems: "
        + ", ".join(args.problems)
        + "; samplers: "
        + ", ".join(args.samplers)
        + (
            " (surmise not installed: skipped)"
            if "surmise" in args.samplers and not surmise_available()
            else ""
        )
        + "."
        + (f" Formulations: {', '.join(args.formulations)} only." if args.formulations else "")
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.usable", description=__doc__)
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    parser.add_argument("--samplers", nargs="+", default=list(SAMPLERS), choices=SAMPLERS)
    parser.add_argument("--formulations", nargs="+", default=None)
    parser.add_argument("--target-ess", type=float, default=1000.0)
    parser.add_argument("--max-rhat", type=float, default=1.01)
    parser.add_argument("--draws", type=int, default=1000)
    parser.add_argument("--tune", type=int, default=1000)
    parser.add_argument("--chains", type=int, default=4)
    parser.add_argument("--max-draws", type=int, default=16_000)
    parser.add_argument("--time-limit", type=float, default=300.0, help="seconds per row")
    parser.add_argument(
        "--attempt-timeout", type=float, default=600.0, help="seconds per attempt (0: none)"
    )
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--quick", action="store_true", help="target ESS 100, 200 draws")
    parser.add_argument("--out", default="benchmarks/results")
    return parser


def main(argv: Sequence[str] | None = None) -> pd.DataFrame:
    """Command-line entry point: run, print and write the tables; return the frame."""
    from benchmarks.run import _quiet

    args = _parser().parse_args(argv)
    _quiet()
    if args.quick:
        args.target_ess, args.draws, args.tune, args.max_draws = 100.0, 200, 200, 800
    machine = f"{platform.node()} ({os.cpu_count()} cores), {time.strftime('%Y-%m-%d %H:%M')}"
    print(f"time to a usable posterior on {machine}", flush=True)
    frame = usable_table(
        args.problems,
        args.samplers,
        formulations=args.formulations,
        target_ess=args.target_ess,
        max_rhat=args.max_rhat,
        draws=args.draws,
        tune=args.tune,
        chains=args.chains,
        max_draws=args.max_draws,
        time_limit=args.time_limit,
        attempt_timeout=args.attempt_timeout or None,
        rwm_draws=2_000 if args.quick else 20_000,
        seed=args.seed,
        progress=lambda line: print(line, flush=True),
    )
    md = write_tables(frame, Path(args.out), settings_header(args, machine))
    print(md, flush=True)
    return frame


if __name__ == "__main__":
    main()
