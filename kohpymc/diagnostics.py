"""Sampler diagnostics reported with every result: r̂, ESS and divergences.

Sampler trouble is never swallowed: :func:`convergence_problems` lists it in plain
words, :func:`kohpymc.calibration.calibrate` stores that list in the InferenceData
attributes (``idata.attrs["sampler_problems"]``) and issues a
:class:`SamplerTroubleWarning`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import arviz as az
import numpy as np
import pandas as pd

from kohpymc.warning_filters import single_chain_notes_hidden

__all__ = [
    "SamplerTroubleWarning",
    "SlowSamplingWarning",
    "sampler_diagnostics",
    "convergence_problems",
    "RHAT_MAX",
    "ESS_MIN",
    "rhat_limit",
]

#: r̂ above this is reported as non-convergence (Vehtari et al. 2021).
RHAT_MAX = 1.01
#: bulk or tail ESS below this (in total) is reported as too few effective draws.
ESS_MIN = 400


class SamplerTroubleWarning(UserWarning):
    """Issued when r̂, ESS, divergences or tree-depth hits indicate an unreliable posterior."""


class SlowSamplingWarning(SamplerTroubleWarning):
    """The sampling run is estimated to take longer than a threshold (before it starts).

    Issued by :class:`kohpymc.presampling.PreSampling`, with the estimate and its reasons.
    """


def n_divergences(idata: az.InferenceData) -> int | None:
    """Number of divergent transitions after tuning, or None if the sampler has none.

    Examples
    --------
    >>> import arviz as az
    >>> n_divergences(az.load_arviz_data("centered_eight")) >= 0  # doctest: +SKIP
    True
    """
    stats = getattr(idata, "sample_stats", None)
    if stats is None or "diverging" not in stats:
        return None
    return int(np.asarray(stats["diverging"]).sum())


def n_max_tree_depth(idata: az.InferenceData) -> int | None:
    """Draws whose NUTS trajectory stopped at the maximum tree depth (None without NUTS).

    nutpie calls the statistic ``maxdepth_reached``, PyMC ``reached_max_treedepth``.

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> idata = az.from_dict(sample_stats={"maxdepth_reached": np.zeros((2, 10), bool)})
    >>> n_max_tree_depth(idata)
    0
    """
    stats = getattr(idata, "sample_stats", None)
    for name in ("maxdepth_reached", "reached_max_treedepth"):
        if stats is not None and name in stats:
            return int(np.asarray(stats[name]).sum())
    return None


def sampler_diagnostics(
    idata: az.InferenceData, var_names: Sequence[str] | None = None
) -> pd.DataFrame:
    """Per-parameter posterior summary with r̂, ESS bulk/tail and the divergence count.

    Parameters
    ----------
    idata : arviz.InferenceData
        A calibration result.
    var_names : sequence of str, optional
        Variables to report; default all posterior variables.

    Returns
    -------
    pandas.DataFrame
        Columns ``mean, sd, q05, q95, r_hat, ess_bulk, ess_tail``; the total number of
        divergences is in ``df.attrs["divergences"]``.

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> rng = np.random.default_rng(0)
    >>> idata = az.from_dict(posterior={"E": rng.normal(size=(2, 500))})
    >>> bool(sampler_diagnostics(idata).loc["E", "r_hat"] < 1.01)
    True
    """
    with single_chain_notes_hidden():
        summary = az.summary(
            idata,
            var_names=list(var_names) if var_names else None,
            kind="all",
            round_to="none",
            stat_funcs={
                "q05": lambda v: np.quantile(v, 0.05),
                "q95": lambda v: np.quantile(v, 0.95),
            },
            extend=True,
        )
    out = summary[["mean", "sd", "q05", "q95", "r_hat", "ess_bulk", "ess_tail"]].copy()
    out.attrs["divergences"] = n_divergences(idata)
    out.attrs["max_tree_depth"] = n_max_tree_depth(idata)
    return out


def rhat_limit(draws: Any, *, parameters: int = 1, level: float = 0.01) -> float:
    """The largest r̂ that well-mixed chains like these reach by chance, at least 1.01.

    Split-r̂ of ``M = 2 × chains`` half-chains of ``n`` draws, each worth ``n_e`` independent
    draws, is ``r̂² ≈ 1 − 1/n + X / n_e`` with ``X ~ χ²_{M−1}/(M−1)`` when the chains mix
    (the variance of the half-chain means is ``σ²/n_e``).  ``n_e`` comes from each
    chain's *own* bulk ESS (summed over the chains, divided by ``M``), so chains that
    disagree do not lower it and so raise their own limit.  The quantile is
    ``1 − level / (2 × parameters)``: ArviZ's r̂ is the larger of the bulk and folded
    (tail) r̂, and a fit is flagged when any of ``parameters`` exceeds its limit, so a
    fit of well-mixed chains is flagged with probability at most about ``level``.
    Never below :data:`RHAT_MAX` (Vehtari et al. 2021), which long chains keep.

    Parameters
    ----------
    draws : array (chain, draw)
        One scalar's posterior draws.
    parameters : int
        Number of parameters whose r̂ is checked in the same fit.
    level : float
        Chance that well-mixed chains of the fit are flagged.

    Returns
    -------
    float

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> rhat_limit(rng.normal(size=(2, 5000)))  # long chains: Vehtari's 1.01
    1.01
    >>> x = np.zeros((2, 400))  # AR(1), ρ = 0.8: 400 draws are worth ~45 per chain
    >>> e = rng.normal(size=(2, 400))
    >>> for t in range(1, 400):
    ...     x[:, t] = 0.8 * x[:, t - 1] + e[:, t]
    >>> 1.05 < rhat_limit(x, parameters=3) < 1.2
    True
    """
    from scipy.stats import chi2

    draws = np.asarray(draws, dtype=float)
    chains, n = draws.shape
    if chains < 2 or n < 4:
        return RHAT_MAX
    with single_chain_notes_hidden():
        within = sum(float(az.ess(draws[c][None, :], method="bulk")) for c in range(chains))
    halves = 2 * chains
    if not (np.isfinite(within) and within > 0):
        return RHAT_MAX
    x = chi2.ppf(1.0 - level / (2 * max(parameters, 1)), halves - 1) / (halves - 1)
    squared = 1.0 - 1.0 / (n // 2) + x * halves / within
    return float(max(RHAT_MAX, np.sqrt(max(squared, 1.0))))


def convergence_problems(
    idata: az.InferenceData,
    var_names: Sequence[str] | None = None,
    *,
    rhat_max: float = RHAT_MAX,
    ess_min: float = ESS_MIN,
) -> list[str]:
    """Plain-language list of sampler problems (empty when none).

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> rng = np.random.default_rng(0)
    >>> bad = az.from_dict(posterior={"E": np.stack([rng.normal(size=300),
    ...                                               rng.normal(5, 1, size=300)])})
    >>> convergence_problems(bad)[0].startswith("r_hat")
    True
    >>> convergence_problems(az.from_dict(posterior={"E": rng.normal(size=(1, 2000))}))
    ['r_hat needs at least 2 chains (1 ran): convergence not checked']
    """
    table = sampler_diagnostics(idata, var_names)
    problems = []
    worst_rhat = table["r_hat"].max()
    chains = int(idata["posterior"].sizes.get("chain", 1))
    if chains < 2:
        problems.append(f"r_hat needs at least 2 chains ({chains} ran): convergence not checked")
    elif np.isnan(worst_rhat) or worst_rhat > rhat_max:
        names = table.index[~(table["r_hat"] <= rhat_max)].tolist()
        problems.append(f"r_hat > {rhat_max} for {names} (max {worst_rhat:.4f})")
    low = table.index[(table["ess_bulk"] < ess_min) | (table["ess_tail"] < ess_min)].tolist()
    if low:
        problems.append(
            f"ESS below {ess_min:g} for {low} "
            f"(min bulk {table['ess_bulk'].min():.0f}, min tail {table['ess_tail'].min():.0f})"
        )
    div = table.attrs.get("divergences")
    if div:
        problems.append(f"{div} divergent transition(s) after tuning")
    depth = table.attrs.get("max_tree_depth")
    if depth:
        problems.append(
            f"{depth} draw(s) stopped at the maximum tree depth (the trajectory was cut short: "
            "a long or curved posterior ridge)"
        )
    return problems
