"""A second NUTS run when the first one's chains show trouble.

PyMC's advice on divergent transitions is a higher target acceptance (a smaller step), and
on a low effective sample size more draws; a careful user does both before reading the
posterior.  After the first run, :func:`plan_second_run` says what a second one changes:

* divergences, when the caller set no ``target_accept``: the target becomes
  :data:`RETRY_TARGET_ACCEPT`;
* chains that mix slowly — a bulk ESS below :func:`ess_wanted` for a sampled parameter,
  or r̂ above :func:`~kohpymc.diagnostics.rhat_limit` — the draws are multiplied (2 to
  :data:`MAX_DRAWS_FACTOR` times, by what the ESS falls short).

It runs only when its projected sampling time, from the first run's, stays within
:data:`MAX_SECOND_RUN_S`; else the trouble is reported as always.  The second run's draws
are the result whatever its diagnostics: choosing between two valid runs by how their
draws came out would select on the draws (a run that missed a hard region diverges
less), while the second run's settings are the better ones before either is seen.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import arviz as az
import numpy as np

from kohpymc.diagnostics import (
    ESS_MIN,
    convergence_problems,
    n_divergences,
    rhat_limit,
    sampler_diagnostics,
)

__all__ = [
    "MAX_DRAWS_FACTOR",
    "MAX_SECOND_RUN_S",
    "RETRY_TARGET_ACCEPT",
    "SecondRun",
    "ess_wanted",
    "mixing",
    "plan_second_run",
]

#: NUTS target acceptance of the second run after divergent transitions.  A few
#: divergences where the curvature rises in one region usually go with a smaller step:
#: enzyme kinetics with substrate inhibition under M4 (natural units, σ unknown) had 7 at
#: 0.95 and none at 0.99, for 1.7x the leapfrog steps; a thermistor's M3 went from 7 to 4.
RETRY_TARGET_ACCEPT = 0.99

#: projected seconds of sampling above which no second run starts
MAX_SECOND_RUN_S = 600.0

#: at most this many times the draws in a second run
MAX_DRAWS_FACTOR = 4

#: leapfrog steps per draw at :data:`RETRY_TARGET_ACCEPT` against the first run's
#: (the enzyme case: 24.5 against 14.1), for the projection
_STEPS_AT_RETRY = 1.75


@dataclass(frozen=True)
class SecondRun:
    """What a second run changes, and why.

    Attributes
    ----------
    target_accept : float
    draws : int
        Kept draws per chain (the tuning steps stay).
    reasons : list of str
        The first run's trouble, in words.
    first_ess : float
        The first run's smallest bulk ESS over the judged parameters.
    """

    target_accept: float
    draws: int
    reasons: list[str]
    first_ess: float


def ess_wanted(chains: int, draws: int) -> float:
    """Bulk ESS below which chains mix too slowly: ``ESS_MIN``, or a tenth of the draws.

    A short run (a test, a quick look) is judged by its length, not by the 400 a
    posterior summary needs.

    Examples
    --------
    >>> ess_wanted(4, 1000), ess_wanted(2, 200)
    (400.0, 40.0)
    """
    return float(min(ESS_MIN, 0.1 * chains * draws))


def plan_second_run(
    idata: az.InferenceData,
    names: Sequence[str],
    *,
    target_accept: float,
    target_fixed: bool,
    tune: int,
    draws: int,
    seconds: float,
) -> SecondRun | None:
    """The second run the first one's chains call for, or None.

    Parameters
    ----------
    idata : InferenceData
        The first run (``posterior``, ``sample_stats``).
    names : sequence of str
        The sampled parameters whose mixing is judged.
    target_accept, target_fixed :
        The first run's target; whether the caller set it (then it stays).
    tune, draws, seconds :
        The first run's tuning steps and draws per chain, and its sampling seconds.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> good = az.from_dict(posterior={"a": rng.normal(size=(4, 1000))},
    ...                     sample_stats={"diverging": np.zeros((4, 1000), bool)})
    >>> plan_second_run(good, ["a"], target_accept=0.9, target_fixed=False, tune=1000,
    ...                 draws=1000, seconds=5.0) is None
    True
    >>> bad = az.from_dict(posterior={"a": rng.normal(size=(4, 1000))},
    ...                    sample_stats={"diverging": np.eye(4, 1000, dtype=bool)})
    >>> plan_second_run(bad, ["a"], target_accept=0.9, target_fixed=False, tune=1000,
    ...                 draws=1000, seconds=5.0).target_accept
    0.99
    """
    reasons: list[str] = []
    new_target = target_accept
    divergent = n_divergences(idata) or 0
    if divergent and not target_fixed and target_accept < RETRY_TARGET_ACCEPT:
        new_target = RETRY_TARGET_ACCEPT
        reasons.append(f"{divergent} divergent transition(s) at target_accept {target_accept}")
    ess, rhat, rhat_max = mixing(idata, names)
    factor, slow = _draws_factor(ess, rhat, rhat_max, ess_wanted(_chains(idata), draws))
    reasons += slow
    if not reasons:
        return None
    steps = _STEPS_AT_RETRY if new_target > target_accept else 1.0
    while factor > 1 and _projected(seconds, tune, draws, factor, steps) > MAX_SECOND_RUN_S:
        factor -= 1
    if _projected(seconds, tune, draws, factor, steps) > MAX_SECOND_RUN_S:
        return None
    if factor == 1 and new_target == target_accept:
        return None
    return SecondRun(new_target, draws * factor, reasons, ess)


def _draws_factor(ess: float, rhat: float, rhat_max: float, wanted: float) -> tuple[int, list[str]]:
    """How many times the draws slow mixing calls for (1: none), and why."""
    reasons = []
    factor = 1
    if ess < wanted:
        reasons.append(f"bulk ESS {ess:.0f} below {wanted:.0f}")
        factor = math.ceil(1.25 * wanted / max(ess, 1.0))
    if rhat > rhat_max:
        reasons.append(f"r_hat {rhat:.4f} above {rhat_max:.4f}")
    if not reasons:
        return 1, []
    return min(max(factor, 2), MAX_DRAWS_FACTOR), reasons


def mixing(idata: az.InferenceData, names: Sequence[str]) -> tuple[float, float, float]:
    """Smallest bulk ESS and largest r̂ over the elements of ``names``, and that r̂'s limit.

    From :func:`~kohpymc.diagnostics.sampler_diagnostics`; the limit is
    :func:`~kohpymc.diagnostics.rhat_limit` of the worst element's draws (``inf``, 1, 1
    when none of ``names`` is drawn; the limit is infinite with one chain).

    Examples
    --------
    >>> rng = np.random.default_rng(2)
    >>> ess, rhat, limit = mixing(az.from_dict(posterior={"a": rng.normal(size=(2, 500))}),
    ...                           ["a"])
    >>> bool(ess > 500), bool(rhat < limit)
    (True, True)
    """
    posterior = idata["posterior"]
    present = [n for n in names if n in posterior]
    if not present:
        return math.inf, 1.0, 1.0
    table = sampler_diagnostics(idata, present)
    rhats = table["r_hat"].to_numpy(float)
    worst = int(np.nanargmax(rhats)) if np.isfinite(rhats).any() else 0
    if _chains(idata) < 2:
        return float(table["ess_bulk"].min()), float(rhats[worst]), math.inf
    # one (chain, draw) array per element, in the table's row order
    columns = [
        column
        for n in present
        for column in np.moveaxis(
            posterior[n]
            .transpose("chain", "draw", ...)
            .values.reshape(posterior.sizes["chain"], posterior.sizes["draw"], -1),
            2,
            0,
        )
    ]
    limit = rhat_limit(columns[worst], parameters=len(columns))
    return float(table["ess_bulk"].min()), float(rhats[worst]), limit


def _chains(idata: az.InferenceData) -> int:
    return int(idata["posterior"].sizes.get("chain", 1))


def _projected(seconds: float, tune: int, draws: int, factor: int, steps: float) -> float:
    """Sampling seconds of a run with ``factor`` times the draws and ``steps`` the steps."""
    return seconds * steps * (tune + factor * draws) / max(tune + draws, 1)


def remaining_after(record: dict[str, Any]) -> str:
    """The note a report of trouble adds when a second run already ran.

    ``record`` is ``SamplingReport.second_run``; the note tells the reader the retry
    ran and did not clear the trouble.

    Examples
    --------
    >>> note = remaining_after({"reasons": ["7 divergences"], "target_accept": [0.95, 0.99],
    ...                         "draws": [1000, 1000], "divergences": [7, 4],
    ...                         "smallest_ess_bulk": [900, 1200]})
    >>> note.split(": ")[1]
    'divergences 7 -> 4, smallest bulk ESS 900 -> 1200'
    """
    (ta0, ta1), (d0, d1) = record["target_accept"], record["draws"]
    (v0, v1), (e0, e1) = record["divergences"], record["smallest_ess_bulk"]
    return (
        f"after a second run ({'; '.join(record['reasons'])}; target_accept {ta0} -> {ta1}, "
        f"draws {d0} -> {d1}): divergences {v0} -> {v1}, smallest bulk ESS {e0} -> {e1}"
    )


def run_problems(idata: az.InferenceData, record: dict[str, Any]) -> list[str]:
    """A run's convergence problems, with a note when a second run did not clear them.

    :func:`~kohpymc.diagnostics.convergence_problems`, then :func:`remaining_after` when
    ``record`` (``SamplingReport.second_run``) says a second run ran.

    Examples
    --------
    >>> import numpy as np
    >>> draws = np.random.default_rng(0).normal(size=(4, 1000))
    >>> run_problems(az.from_dict(posterior={"E": draws}), {})
    []
    """
    problems = convergence_problems(idata)  # SMC: r̂ between its independent runs
    if problems and record:
        problems.append(remaining_after(record))
    return problems
