"""Figures: the validation panels for grouped and for scattered designs."""

from __future__ import annotations

import arviz as az
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.container import ErrorbarContainer

from kohpymc.plots import plot_validation_predictions


def _predictions(n, seed=0):
    rng = np.random.default_rng(seed)
    draws = rng.normal(size=(2, 50, n))
    return az.from_dict(predictions={"y_pred": draws}, dims={"y_pred": ["pred"]})


def test_a_few_series_get_bands_and_a_scattered_design_gets_per_point_intervals():
    rng = np.random.default_rng(1)
    x = np.tile(np.linspace(0.0, 1.0, 10), 2)
    grouped = {"x": x, "P": np.repeat([1.0, 2.0], 10)}
    fig = plot_validation_predictions({"M0": _predictions(20)}, rng.normal(size=20), grouped)
    ax = fig.axes[0]
    assert sum(isinstance(c, PolyCollection) for c in ax.collections) == 2  # one band a series
    assert not any(isinstance(c, ErrorbarContainer) for c in ax.containers)
    plt.close(fig)
    # two continuous inputs: every row its own "series" -> per-point intervals instead
    scattered = {"T": rng.uniform(300, 400, 20), "c": rng.uniform(0.5, 2.0, 20)}
    y = rng.normal(size=20)
    fig = plot_validation_predictions({"M0": _predictions(20)}, y, scattered)
    ax = fig.axes[0]
    (bars,) = [c for c in ax.collections if isinstance(c, LineCollection)]
    assert len(bars.get_segments()) == 20
    assert not any(isinstance(c, PolyCollection) for c in ax.collections)
    plt.close(fig)


def test_a_mean_outside_its_own_90_percent_interval_is_drawn():
    """A skewed predictive distribution (one draw in a hundred far out, as a log-variance
    extrapolated beyond the calibration inputs gives) puts the mean above the 95 % quantile;
    the scattered design's per-point interval raised "'yerr' must not contain negative
    values" and failed the study's figures (a Hill curve under M3 from kp.run_study)."""
    rng = np.random.default_rng(3)
    draws = rng.normal(size=(2, 50, 6))
    draws[0, 0, :] = 1e4  # mean ~ 100, 95 % quantile ~ 2
    pred = az.from_dict(predictions={"y_pred": draws}, dims={"y_pred": ["pred"]})
    scattered = {"T": rng.uniform(300, 400, 6), "c": rng.uniform(0.5, 2.0, 6)}
    fig = plot_validation_predictions({"M3": pred}, rng.normal(size=6), scattered)
    ax = fig.axes[0]
    (bars,) = [c for c in ax.collections if isinstance(c, LineCollection)]
    tops = np.array([seg[:, 1].max() for seg in bars.get_segments()])
    means = [line for line in ax.lines if line.get_label() == "mean"][0].get_ydata()
    assert np.all(means > tops)  # drawn where it is, outside the band
    assert not any(isinstance(c, ErrorbarContainer) for c in ax.containers)
    plt.close(fig)


def test_a_parameter_spanning_decades_is_drawn_on_a_log_axis():
    from kohpymc.plots import plot_parameter_posteriors

    rng = np.random.default_rng(2)
    wide = az.from_dict(posterior={"A": np.exp(rng.normal(18.0, 2.0, (2, 300))),
                                   "E": rng.normal(200.0, 5.0, (2, 300))})  # fmt: skip
    fig = plot_parameter_posteriors({"M0": wide}, ["A", "E"], reference={"A": 6.5e7})
    assert [ax.get_xlabel() for ax in fig.axes] == ["log10 A", "E"]
    low, high = fig.axes[0].get_xlim()
    assert low < np.log10(6.5e7) < high < 30  # log10 values, not raw ones
    plt.close(fig)
