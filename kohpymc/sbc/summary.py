"""From replicate results to a coverage table and a verdict.

Coverage of the central 50 % and 90 % intervals with binomial standard errors, the rank
histogram's chi-square test, and the PASS/FAIL line (see :mod:`kohpymc.sbc`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

__all__ = ["coverage_table", "prior_data_note", "rank_uniformity", "verdict"]

#: the two central intervals whose coverage is checked
LEVELS = (0.5, 0.9)
#: null standard errors a coverage may be off before the verdict fails
COVERAGE_Z = 3.0
#: chi-square p-value below which ranks are not uniform
UNIFORMITY_ALPHA = 1e-3
#: fraction of replicates with sampler trouble above which the check fails
MAX_FLAGGED = 0.10
#: a replicate whose data's sd is below this many noise sds is called mostly noise
NOISE_ONLY_RATIO = 1.5
#: a replicate whose data's sd differs from the calibration data's by this factor is off scale
OFF_SCALE_FACTOR = 100.0


def rank_uniformity(ranks: np.ndarray, n_ranked: int) -> tuple[float, int, np.ndarray]:
    """Chi-square test that ranks ``0 … L`` are uniform: p-value, bins and bin counts.

    The ``L + 1`` rank values are pooled into ``B`` equal bins (``B`` divides ``L + 1``,
    at most 20, at least 5 expected counts per bin when possible).

    Examples
    --------
    >>> p, bins, counts = rank_uniformity(np.arange(100), 99)
    >>> round(p, 3), bins, counts.tolist()[:3]
    (1.0, 20, [5, 5, 5])
    """
    ranks = np.asarray(ranks, dtype=int)
    values = n_ranked + 1
    divisors = [b for b in range(min(20, values), 0, -1) if values % b == 0]
    enough = [b for b in divisors if ranks.size / b >= 5]
    bins = enough[0] if enough else divisors[-1]
    counts = np.bincount(ranks * bins // values, minlength=bins)
    if bins < 2:
        return float("nan"), bins, counts
    return float(stats.chisquare(counts).pvalue), bins, counts


def coverage_table(records: list[dict], parameters: list[str], n_ranked: int) -> pd.DataFrame:
    """Per parameter: coverage of the 50 % and 90 % intervals with binomial SEs, ranks.

    Examples
    --------
    >>> rec = [{"cover50": {"a": i % 2 == 0}, "cover90": {"a": True}, "rank": {"a": i}}
    ...        for i in range(10)]
    >>> coverage_table(rec, ["a"], 9).loc["a", ["cover50", "cover90", "mean_rank"]].tolist()
    [0.5, 1.0, 0.5]
    """
    rows = {}
    n = len(records)
    for name in parameters:
        row: dict[str, Any] = {"replicates": n}
        for level in LEVELS:
            key = f"cover{round(100 * level)}"
            p = float(np.mean([r[key][name] for r in records])) if n else float("nan")
            row[key] = p
            row[f"{key}_se"] = float(np.sqrt(p * (1 - p) / n)) if n else float("nan")
        ranks = np.array([r["rank"][name] for r in records], dtype=int)
        row["mean_rank"] = float(ranks.mean() / n_ranked) if n else float("nan")
        row["chi2_p"], row["rank_bins"], _ = rank_uniformity(ranks, n_ranked)
        rows[name] = row
    frame = pd.DataFrame.from_dict(rows, orient="index")
    frame.index.name = "parameter"
    return frame


def verdict(table: pd.DataFrame, n_finished: int, n_flagged: int, label: str) -> tuple[bool, str]:
    """PASS or FAIL with the reasons, from the coverage table (see the module docstring).

    Examples
    --------
    >>> t = pd.DataFrame({"replicates": [200], "cover50": [0.5], "cover50_se": [0.035],
    ...                   "cover90": [0.41], "cover90_se": [0.0348], "chi2_p": [0.3]},
    ...                  index=["sigma_obs"])
    >>> print(verdict(t, 200, 0, "M0")[1])  # doctest: +NORMALIZE_WHITESPACE
    FAIL: sigma_obs 90 % coverage 0.41 ± 0.03 (expected 0.90): the set-up does not recover
    the truth
    """
    trouble = ""
    if n_finished and n_flagged / n_finished > MAX_FLAGGED:
        trouble = (
            f"{n_flagged} of {n_finished} replicates had sampler trouble (more than "
            f"{MAX_FLAGGED:.0%}; leaving them out biases the check): longer chains "
            "(--draws/--tune) or a better-posed set-up needed"
        )
    reasons = []
    for name, row in table.iterrows():
        n = int(row["replicates"])
        if n == 0:
            continue
        for level in (0.9, 0.5):
            key = f"cover{round(100 * level)}"
            if abs(row[key] - level) > COVERAGE_Z * np.sqrt(level * (1 - level) / n):
                reasons.append(
                    f"{name} {round(100 * level)} % coverage {row[key]:.2f} ± "
                    f"{row[key + '_se']:.2f} (expected {level:.2f})"
                )
        if row["chi2_p"] < UNIFORMITY_ALPHA:
            reasons.append(f"{name} ranks not uniform (chi-square p = {row['chi2_p']:.2g})")
    if reasons:
        text = "; ".join(reasons) + ": the set-up does not recover the truth"
        return False, "FAIL: " + text + (f"; also {trouble}" if trouble else "")
    if trouble:
        return False, "FAIL: " + trouble
    covers = ", ".join(
        f"{row['cover90']:.2f} ± {row['cover90_se']:.2f} ({name})" for name, row in table.iterrows()
    )
    n_used = int(table["replicates"].iloc[0]) if len(table) else 0
    tolerance = COVERAGE_Z * np.sqrt(0.9 * 0.1 / max(n_used, 1))
    weak = f"; only {n_used} replicates: a coarse check" if n_used < 50 else ""
    return True, (
        f"PASS: {label}, {n_used} replicates: every parameter's 90 % interval covers the truth "
        f"({covers}; allowed 0.90 ± {tolerance:.2f}); 50 % coverage and rank histograms "
        f"consistent with uniform ranks{weak}"
    )


def _unlike_the_data(y: np.ndarray, noise_sd: float | None, observed_sd: float) -> str:
    """``"noise"``, ``"scale"`` or ``""``: how one replicate's data differ from the real ones."""
    spread = float(np.std(y))
    if noise_sd is not None and noise_sd > 0 and spread < NOISE_ONLY_RATIO * noise_sd:
        return "noise"
    if observed_sd > 0 and not (
        observed_sd / OFF_SCALE_FACTOR <= spread <= observed_sd * OFF_SCALE_FACTOR
    ):
        return "scale"
    return ""


def prior_data_note(
    records: list[dict[str, Any]], observed: np.ndarray, noise_sd: float | None = None
) -> str:
    """Why replicates with sampler trouble may be the priors' doing, or ``""``.

    A simulation-based check draws its truths from the priors. When the priors reach values
    where the model's output varies less than the noise (the data are mostly noise) or on a
    scale far from the real data's, those replicates cannot be calibrated, and their sampler
    trouble says more about the priors than about the sampler. This counts, among the
    replicates with trouble, those whose data's sd is below ``NOISE_ONLY_RATIO`` noise sds
    (the replicate's own ``sigma_obs``, else ``noise_sd``) or outside
    ``1 / OFF_SCALE_FACTOR … OFF_SCALE_FACTOR`` times the observed data's sd; the note is
    returned when they are at least half of them.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> records = [
    ...     {"problems": ["3 divergences"], "y": rng.normal(0, 0.1, 20),
    ...      "truth": {"sigma_obs": 0.1}},
    ...     {"problems": ["r_hat 1.2"], "y": 1e6 * rng.normal(size=20),
    ...      "truth": {"sigma_obs": 0.1}},
    ...     {"problems": [], "y": rng.normal(0, 5, 20), "truth": {"sigma_obs": 0.1}},
    ... ]
    >>> print(prior_data_note(records, rng.normal(0, 5, 20)))  # doctest: +NORMALIZE_WHITESPACE
    2 of the 2 replicates with sampler trouble had data unlike the calibration data (1 mostly
    noise, 1 on a scale 100 times off): the priors reach values where the model cannot be
    calibrated from such data; narrowing them to physically plausible values (check the
    prior's predictions) makes the check meaningful
    """
    troubled = [r for r in records if r["problems"]]
    observed_sd = float(np.std(np.asarray(observed, dtype=float)))
    kinds = [
        _unlike_the_data(
            np.asarray(r["y"], dtype=float), r["truth"].get("sigma_obs", noise_sd), observed_sd
        )
        for r in troubled
    ]
    unlike = sum(bool(k) for k in kinds)
    if not troubled or 2 * unlike < len(troubled):
        return ""
    return (
        f"{unlike} of the {len(troubled)} replicates with sampler trouble had data unlike the "
        f"calibration data ({kinds.count('noise')} mostly noise, {kinds.count('scale')} on a "
        f"scale {OFF_SCALE_FACTOR:g} times off): the priors reach values where the model "
        "cannot be calibrated from such data; narrowing them to physically plausible values "
        "(check the prior's predictions) makes the check meaningful"
    )
