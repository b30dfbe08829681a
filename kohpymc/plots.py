"""Figures of a study, after the paper's figures.

Parameter posteriors per formulation (Figs. 4 and 7), predictions with 90 % bands
against validation data (Figs. 5, 6 and 8) and the validation metric per formulation.

All functions take InferenceData / tables produced by :mod:`kohpymc.study` (or by
:func:`kohpymc.calibrate` and :func:`kohpymc.predict`) and return a matplotlib Figure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import arviz as az
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

__all__ = [
    "plot_parameter_posteriors",
    "plot_validation_predictions",
    "plot_reliability",
    "plot_residuals_before_after",
]

_COMBINED = "combined"


def plot_parameter_posteriors(
    results: Mapping[str, az.InferenceData],
    var_names: Sequence[str],
    *,
    combined: az.InferenceData | None = None,
    reference: Mapping[str, float] | None = None,
) -> plt.Figure:
    """Marginal posterior densities of the physics parameters, one curve per formulation.

    A positive parameter whose draws span two decades or more (1st to 99th percentile)
    is drawn on a log10 axis (the axis label says so).

    Parameters
    ----------
    results : mapping label -> InferenceData
        Calibrations.
    var_names : sequence of str
        Physics parameters (one panel each).
    combined : InferenceData, optional
        The reliability-weighted mixture, drawn as a dashed black curve.
    reference : mapping, optional
        Known values (e.g. the synthetic truth) drawn as vertical lines.

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> rng = np.random.default_rng(0)
    >>> res = {"M0": az.from_dict(posterior={"E": rng.normal(110, 1, (2, 200))}),
    ...        "M4": az.from_dict(posterior={"E": rng.normal(200, 30, (2, 200))})}
    >>> fig = plot_parameter_posteriors(res, ["E"], reference={"E": 200.0})
    >>> len(fig.axes)
    1
    """
    names = list(var_names)
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        curves = {label: idata.posterior[name].values.ravel() for label, idata in results.items()}
        if combined is not None and name in combined.posterior:
            curves[_COMBINED] = combined.posterior[name].values.ravel()
        log = _spans_decades(np.concatenate(list(curves.values())))
        for i, (label, values) in enumerate(curves.items()):
            style = {"color": "k", "linestyle": "--"} if label == _COMBINED else {"color": f"C{i}"}
            az.plot_kde(np.log10(values) if log else values, ax=ax,
                        plot_kwargs={**style, "label": label})  # fmt: skip
        if reference and name in reference:
            value = np.log10(reference[name]) if log else reference[name]
            ax.axvline(value, color="0.4", linewidth=1, label="reference")
        ax.set_xlabel(f"log10 {name}" if log else name)
        ax.set_ylabel("posterior density")
    axes[0][0].legend(fontsize="small")
    fig.tight_layout()
    return fig


def _spans_decades(values: np.ndarray) -> bool:
    """Positive draws spread over two decades or more: plotted on a log10 axis."""
    finite = values[np.isfinite(values)]
    if finite.size == 0 or np.any(finite <= 0):
        return False
    lo, hi = np.quantile(finite, [0.01, 0.99])
    return bool(hi / lo >= 100.0)


def _main_input(coords: Mapping[str, np.ndarray]) -> str:
    """The input with most distinct values (the x-axis of a prediction plot)."""
    return max(coords, key=lambda k: (np.unique(coords[k]).size, -list(coords).index(k)))


def plot_validation_predictions(
    predictions: Mapping[str, az.InferenceData],
    y_validation: np.ndarray,
    inputs: Mapping[str, np.ndarray],
    *,
    x_input: str | None = None,
    var_name: str = "y_pred",
    output_name: str = "y",
) -> plt.Figure:
    """Posterior mean and 90 % band of the predictions against validation data.

    One panel per formulation (and per mixture).  The x-axis is ``x_input`` (default: the
    input with the most distinct values); rows that differ in the other inputs are drawn
    as separate series (the paper's Figs. 5/6/8).  When the other inputs do not form a
    few series (a scattered design: more than 8 groups, or mostly single rows), every
    validation point gets its own vertical 90 % interval and posterior mean instead.

    Parameters
    ----------
    predictions : mapping label -> InferenceData
        Each with a ``predictions`` group at the validation inputs.
    y_validation : array
        Validation measurements, one per prediction point.
    inputs : mapping name -> array
        Validation input values.
    x_input : str, optional
        Input on the x-axis.
    var_name : str
        ``"y_pred"`` (with measurement noise) or ``"y_model"``.
    output_name : str
        Label of the y-axis.

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> x = np.linspace(0, 1, 5)
    >>> pred = az.from_dict(predictions={"y_pred": np.tile(x, (2, 50, 1))},
    ...                     dims={"y_pred": ["pred"]})
    >>> fig = plot_validation_predictions({"M0": pred}, x, {"x": x})
    >>> len(fig.axes)
    1
    """
    inputs = {k: np.asarray(v) for k, v in inputs.items()}
    x_input = x_input or _main_input(inputs)
    others = [k for k in inputs if k != x_input]
    groups = _series_groups(inputs, others, len(y_validation))
    labels = list(predictions)
    ncol = min(3, len(labels))
    nrow = int(np.ceil(len(labels) / ncol))
    fig, axes = plt.subplots(
        nrow, ncol, figsize=(4.2 * ncol, 3.3 * nrow), squeeze=False, sharey=True
    )
    x_all = inputs[x_input]
    scattered = len(groups) > 8 or np.median([len(i) for i in groups.values()]) < 3
    for ax, label in zip(axes.ravel(), labels, strict=False):
        mean, lo, hi = _prediction_band(predictions[label], var_name)
        if scattered:
            _pointwise_bands(ax, x_all, mean, lo, hi, np.asarray(y_validation))
        else:
            _series_bands(ax, x_all, groups, others, mean, lo, hi, np.asarray(y_validation))
        ax.set_title(label)
        ax.set_xlabel(x_input)
        ax.set_ylabel(output_name)
    for ax in axes.ravel()[len(labels) :]:
        ax.set_visible(False)
    if (others and len(groups) <= 12) or scattered:
        axes.ravel()[0].legend(fontsize="x-small")
    fig.suptitle("posterior mean, 90 % band and validation data", fontsize="medium")
    fig.tight_layout()
    return fig


def _series_groups(
    inputs: Mapping[str, np.ndarray], others: list[str], n: int
) -> dict[Any, np.ndarray]:
    """Rows of every combination of the ``others`` inputs' values (one series each)."""
    if not others:
        return {(): np.arange(n)}
    return pd.DataFrame({k: inputs[k] for k in others}).groupby(others, sort=True).indices


def _prediction_band(idata: az.InferenceData, var_name: str):
    """Posterior mean and 5 % and 95 % quantiles of ``var_name`` per prediction point."""
    draws = idata.predictions[var_name].transpose(..., "pred").values
    draws = draws.reshape(-1, draws.shape[-1])
    mean = draws.mean(axis=0)
    lo, hi = np.quantile(draws, [0.05, 0.95], axis=0)
    return mean, lo, hi


def _series_bands(ax, x_all, groups, others, mean, lo, hi, y_validation) -> None:
    """One band, mean line and data series per group of rows, coloured in turn."""
    for j, (key, idx) in enumerate(groups.items()):
        idx = np.asarray(idx)[np.argsort(x_all[idx], kind="stable")]
        # one band point per distinct x (replicated rows share their prediction)
        line = idx[np.unique(x_all[idx], return_index=True)[1]]
        color = f"C{j % 10}"
        ax.fill_between(x_all[line], lo[line], hi[line], color=color, alpha=0.25, lw=0)
        ax.plot(x_all[line], mean[line], color=color, lw=1.5)
        tag = ", ".join(f"{k}={v:g}" for k, v in zip(others, np.atleast_1d(key), strict=True))
        ax.plot(
            x_all[idx], y_validation[idx], "o", ms=3.5, color=color,
            mec="k", mew=0.4, label=tag or None,
        )  # fmt: skip


def _pointwise_bands(ax, x, mean, lo, hi, y) -> None:
    """A vertical 90 % interval and the mean at every validation point, the data on top.

    The interval and the mean are drawn apart: a skewed predictive distribution (a
    log-variance extrapolated beyond the calibration inputs) can put the mean outside
    its own 5–95 % interval, which an error bar around the mean cannot show.
    """
    ax.vlines(x, lo, hi, color="C0", alpha=0.6, lw=1.2, label="90 % band")
    ax.plot(x, mean, "_", color="C0", alpha=0.6, ms=8, label="mean")
    ax.plot(x, y, "o", ms=3.5, color="k", label="validation data")


def plot_reliability(table: pd.DataFrame) -> plt.Figure:
    """Bar chart of μ_r with ±2 Monte-Carlo standard errors, weights written on the bars.

    Parameters
    ----------
    table : pandas.DataFrame
        Indexed by formulation with columns ``mu_r``, ``mu_r_mcse`` and optionally
        ``weight`` (a study's table).

    Examples
    --------
    >>> import pandas as pd
    >>> table = pd.DataFrame({"mu_r": [0.3, 0.6], "mu_r_mcse": [0.01, 0.01],
    ...                       "weight": [1 / 3, 2 / 3]}, index=["M0", "M1"])
    >>> len(plot_reliability(table).axes)
    1
    """
    rows = table.dropna(subset=["mu_r"])
    fig, ax = plt.subplots(figsize=(1.1 * len(rows) + 2.5, 3.4))
    colors = ["0.3" if k == _COMBINED else f"C{i}" for i, k in enumerate(rows.index)]
    pos = np.arange(len(rows))
    ax.bar(pos, rows["mu_r"], yerr=2 * rows["mu_r_mcse"].fillna(0), color=colors, capsize=4)
    if "weight" in rows:
        for p, (m, w) in enumerate(zip(rows["mu_r"], rows["weight"], strict=True)):
            if np.isfinite(w):
                ax.text(p, m + 0.02, f"w={w:.2f}", ha="center", fontsize="small")
    ax.set_xticks(pos, [str(k) for k in rows.index])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel(r"$\mu_r$ (validation reliability)")
    fig.tight_layout()
    return fig


def plot_residuals_before_after(
    x: np.ndarray,
    before: np.ndarray,
    after: np.ndarray,
    *,
    x_name: str = "x",
    groups: np.ndarray | None = None,
    noise_sd: float | None = None,
) -> plt.Figure:
    """Residuals of the data from the posterior-mean model before and after a change.

    Parameters
    ----------
    x : array
        Input on the horizontal axis (the one the discrepancy depends on most).
    before, after : array
        Residuals ``y - E[y_model]`` of the same rows.
    x_name : str
        Axis label.
    groups : array, optional
        A label per row (e.g. the other inputs) to colour by.
    noise_sd : float, optional
        Draw ±2 σ_obs as a band.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0, 1, 10)
    >>> len(plot_residuals_before_after(x, x, 0 * x, noise_sd=0.1).axes)
    2
    """
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
    labels = np.zeros(len(x), dtype=int) if groups is None else np.asarray(groups)
    for ax, values, title in zip(axes, (before, after), ("before", "after"), strict=True):
        for j, g in enumerate(np.unique(labels)):
            m = labels == g
            ax.plot(np.asarray(x)[m], np.asarray(values)[m], "o", ms=3.5, color=f"C{j % 10}",
                    label=None if groups is None else str(g))  # fmt: skip
        if noise_sd:
            ax.axhspan(-2 * noise_sd, 2 * noise_sd, color="0.85", zorder=0)
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_title(f"residuals {title}")
        ax.set_xlabel(x_name)
    axes[0].set_ylabel("data - posterior mean")
    if groups is not None:
        axes[0].legend(fontsize="x-small")
    fig.tight_layout()
    return fig
