"""Reliability-weighted combination of formulations (paper Section 5.2, Eqs. 23–24).

Weights ``w_i = μ_r,i / Σ_j μ_r,j`` (Eq. 23); the averaged posterior (Eq. 24) is the
mixture ``Σ_i w_i π(θ, δ | D, M_i)``, represented by resampling draws: formulation ``i``
contributes ``round(w_i · N)`` draws (largest-remainder rounding, so counts add up to
``N``) taken without replacement from its pooled chains when it has enough, with
replacement otherwise, in shuffled order.  A ``formulation`` coordinate along ``draw``
records where every draw came from.

For comparison, :func:`loo_weights` gives the weights ArviZ's ``az.compare`` assigns on
the *calibration* data (PSIS-LOO stacking or pseudo-BMA), whereas the paper's weights
use the *validation* data.  The GP formulations store exact leave-one-out conditional
densities as their pointwise log-likelihood (:mod:`kohpymc.loo`), so LOO sees every
observation there too.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr

__all__ = ["reliability_weights", "combine_posteriors", "loo_weights"]


def reliability_weights(mu_r: Mapping[str, float]) -> dict[str, float]:
    """Normalised reliability weights (Eq. 23).

    Examples
    --------
    >>> round(reliability_weights({"M0": 0.5, "M1": 0.66})["M1"], 4)
    0.569
    """
    values = {k: float(v) for k, v in mu_r.items()}
    if not values:
        raise ValueError("no formulations to weight")
    bad = [k for k, v in values.items() if not np.isfinite(v) or v < 0]
    if bad:
        raise ValueError(f"mu_r must be finite and non-negative; bad for {bad}")
    total = sum(values.values())
    if total <= 0:
        raise ValueError("all mu_r are zero: no formulation predicts within the tolerance")
    return {k: v / total for k, v in values.items()}


def loo_weights(
    results: Mapping[str, az.InferenceData],
    method: str = "stacking",
    var_name: str = "y",
) -> pd.DataFrame:
    """LOO model comparison on the calibration data (``az.compare``).

    Parameters
    ----------
    results : mapping label -> InferenceData
        Calibrations with a pointwise ``log_likelihood`` group (as :func:`calibrate`
        stores).
    method : {"stacking", "BB-pseudo-BMA", "pseudo-BMA"}
        ArviZ's weighting method.
    var_name : str
        Log-likelihood variable.

    Returns
    -------
    pandas.DataFrame
        ``az.compare``'s table (``elpd_loo``, ``p_loo``, ``weight``, ``warning`` ...)
        indexed by formulation, in the order of ``results``, plus ``max_pareto_k``.

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> rng = np.random.default_rng(0)
    >>> good = az.from_dict(posterior={"a": rng.normal(size=(2, 100))},
    ...                     log_likelihood={"y": rng.normal(-1.0, 0.01, size=(2, 100, 10))})
    >>> bad = az.from_dict(posterior={"a": rng.normal(size=(2, 100))},
    ...                    log_likelihood={"y": rng.normal(-3.0, 0.01, size=(2, 100, 10))})
    >>> table = loo_weights({"good": good, "bad": bad})
    >>> bool(table.loc["good", "weight"] > 0.99)
    True
    """
    if len(results) < 2:
        raise ValueError("LOO weights need at least two formulations")
    for label, idata in results.items():
        if "log_likelihood" not in idata.groups() or var_name not in idata.log_likelihood:
            raise KeyError(f"{label}: no log_likelihood variable {var_name!r}")
        if idata.log_likelihood[var_name].ndim < 3:
            raise ValueError(f"{label}: log-likelihood {var_name!r} is not pointwise")
    loos = {k: az.loo(v, pointwise=True, var_name=var_name) for k, v in results.items()}
    table = az.compare(loos, ic="loo", method=method)
    table["max_pareto_k"] = [float(np.max(loos[k].pareto_k)) for k in table.index]
    return table.loc[list(results)]


def _counts(weights: Sequence[float] | np.ndarray, total: int) -> np.ndarray:
    raw = np.asarray(weights, dtype=float) * total
    counts = np.floor(raw).astype(int)
    short = total - counts.sum()
    order = np.argsort(-(raw - counts), kind="stable")
    counts[order[:short]] += 1
    return counts


def _stack(ds: xr.Dataset) -> xr.Dataset:
    return ds.stack(sample=("chain", "draw")).reset_index("sample", drop=True)


def combine_posteriors(
    results: Mapping[str, az.InferenceData],
    weights: Mapping[str, float],
    *,
    var_names: Sequence[str] | None = None,
    predictions: Mapping[str, az.InferenceData] | None = None,
    draws: int | None = None,
    random_seed: int | None = None,
) -> az.InferenceData:
    """Weighted mixture of posteriors (and predictions) as one InferenceData (Eq. 24).

    Parameters
    ----------
    results : mapping label -> InferenceData
        Calibrations under different formulations.
    weights : mapping label -> float
        Mixture weights (e.g. :func:`reliability_weights`); normalised here.
    var_names : sequence of str, optional
        Posterior variables to combine; default those present in every result (the
        shared physics parameters).
    predictions : mapping label -> InferenceData, optional
        Prediction results (same ``pred`` points) to combine with the same draws.
    draws : int, optional
        Number of combined draws; default the size of the smallest posterior.
    random_seed : int, optional
        Seed of the resampling.

    Returns
    -------
    arviz.InferenceData
        ``posterior`` (and ``predictions``) with dims ``(chain=1, draw)`` and a
        ``formulation`` coordinate on ``draw``; ``attrs["weights"]`` holds the weights.

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> a = az.from_dict(posterior={"E": np.full((2, 50), 1.0)})
    >>> b = az.from_dict(posterior={"E": np.full((2, 50), 3.0)})
    >>> mix = combine_posteriors({"A": a, "B": b}, {"A": 0.25, "B": 0.75}, random_seed=0)
    >>> float(mix.posterior["E"].mean())
    2.5
    """
    labels, w = _mixture_weights(results, weights)
    posts = {k: _stack(results[k].posterior) for k in labels}
    var_names = _combined_vars(results[labels[0]], posts, var_names)
    sizes = {k: p.sizes["sample"] for k, p in posts.items()}
    total = int(draws or min(sizes.values()))
    draw = _draw_plan(labels, w, sizes, total, random_seed)
    groups = {"posterior": draw.mix(posts, var_names)}
    if predictions is not None:
        preds = {k: _stack(predictions[k].predictions) for k in labels}
        pred_vars = [v for v in preds[labels[0]].data_vars if all(v in p for p in preds.values())]
        groups["predictions"] = draw.mix(preds, pred_vars)
    combined = az.InferenceData(**groups)
    combined.attrs["weights"] = str({k: float(x) for k, x in zip(labels, w, strict=True)})
    return combined


def _mixture_weights(
    results: Mapping[str, az.InferenceData], weights: Mapping[str, float]
) -> tuple[list[str], np.ndarray]:
    """The formulations with a positive weight and their normalised weights."""
    labels = [k for k in results if weights.get(k, 0.0) > 0]
    if not labels:
        raise ValueError("no formulation has a positive weight")
    missing = [k for k in weights if k not in results]
    if missing:
        raise KeyError(f"weights name formulations without results: {missing}")
    w = np.array([weights[k] for k in labels], dtype=float)
    return labels, w / w.sum()


def _combined_vars(
    first: az.InferenceData, posts: Mapping[str, xr.Dataset], var_names: Sequence[str] | None
) -> Sequence[str]:
    """The variables to combine: ``var_names`` (checked), else those every posterior has."""
    if var_names is None:
        shared = set.intersection(*(set(p.data_vars) for p in posts.values()))
        return [v for v in first.posterior.data_vars if v in shared]
    for k, p in posts.items():
        absent = [v for v in var_names if v not in p]
        if absent:
            raise KeyError(f"{k}: posterior lacks {absent}")
    return var_names


@dataclass(frozen=True)
class _DrawPlan:
    """Which stacked draws of each formulation make the mixture, and in what order."""

    labels: list[str]
    picks: dict[str, np.ndarray]  # label -> positions in its stacked draws
    origin: np.ndarray  # formulation of each picked draw, before the shuffle
    order: np.ndarray  # the shuffle
    total: int

    def mix(self, groups: Mapping[str, xr.Dataset], names: Sequence[str]) -> xr.Dataset:
        """The picked draws of ``names`` as one shuffled chain with a formulation coordinate."""
        parts = [groups[k][list(names)].isel(sample=self.picks[k]) for k in self.labels]
        out = xr.concat(parts, dim="sample").isel(sample=self.order).rename({"sample": "draw"})
        out = out.assign_coords(
            draw=np.arange(self.total), formulation=("draw", self.origin[self.order].astype(str))
        )
        return out.expand_dims(chain=[0]).transpose("chain", "draw", ...)


def _draw_plan(
    labels: list[str],
    w: np.ndarray,
    sizes: Mapping[str, int],
    total: int,
    random_seed: int | None,
) -> _DrawPlan:
    """Pick ``total`` draws, each formulation's share by its weight, and shuffle them."""
    counts = _counts(w, total)
    rng = np.random.default_rng(random_seed)
    picks = {}
    for k, n in zip(labels, counts, strict=True):
        picks[k] = rng.choice(sizes[k], size=n, replace=n > sizes[k])
    origin = np.concatenate(
        [np.full(n, k, dtype=object) for k, n in zip(labels, counts, strict=True)]
    )
    # shuffle so the single "chain" is not sorted by formulation (its autocorrelation,
    # hence ArviZ's ESS/MCSE of the mixture, then reflects independent resampling)
    order = rng.permutation(total)
    return _DrawPlan(labels, picks, origin, order, total)
