r"""Reliability-based validation metric (paper Section 5.1, Eqs. 19–22).

At a validation input x the reliability is :math:`r(x) = \Pr(|y_D - y_m| < \epsilon)`
(Eq. 19) with :math:`y_m` the posterior prediction of ``G + δ`` (Eq. 20, the
``y_model`` draws of :func:`kohpymc.predict`) and :math:`y_D \sim N(D, \sigma_{obs}^2)`
(or, with replicate measurements at x, normal with their mean and variance).

The integral over :math:`y_D` is done exactly: for each posterior draw :math:`y_m^s`,

.. math::

    \Pr(|y_D - y_m^s| < \epsilon) = \Phi\Big(\frac{y_m^s + \epsilon - D}{\sigma}\Big)
                                  - \Phi\Big(\frac{y_m^s - \epsilon - D}{\sigma}\Big),

so only the posterior draws are Monte Carlo, with no second layer of sampling.  The
overall metric is the weighted mean :math:`\mu_r = \sum_i w_i r(x_i) / \sum_i w_i`
(Eq. 22, uniform weights by default).  Its Monte-Carlo standard error comes from the
per-draw averages :math:`q_s = \sum_i w_i p_{is} / \sum_i w_i` (whose mean is μ_r) with
ArviZ's autocorrelation-aware MCSE.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr
from scipy.special import ndtr

from kohpymc.data import CalibrationData

__all__ = ["Reliability", "reliability"]


@dataclass
class Reliability:
    """Pointwise reliability, its weighted mean and the Monte-Carlo standard error.

    Attributes
    ----------
    pointwise : xarray.DataArray
        ``r(x_i)`` over the ``pred`` dimension (with the input values as coordinates).
    mu_r : float
        Weighted mean reliability (Eq. 22).
    mcse : float
        Monte-Carlo standard error of ``mu_r``.
    tolerance : float
        ε.
    """

    pointwise: xr.DataArray
    mu_r: float
    mcse: float
    tolerance: float

    def to_dataset(self) -> xr.Dataset:
        """The result as an xarray Dataset (storable in an InferenceData group)."""
        ds = xr.Dataset({"reliability": self.pointwise})
        ds.attrs.update({"mu_r": self.mu_r, "mu_r_mcse": self.mcse, "tolerance": self.tolerance})
        return ds


def _measurement_model(
    validation: CalibrationData, noise_sd: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sd of y_D at every validation row."""
    sd = noise_sd if noise_sd is not None else validation.noise_sd
    if validation.replicates is not None:
        frame = pd.DataFrame({"y": validation.y, "g": validation.replicates})
        grouped = frame.groupby("g", sort=False)["y"]
        mean = grouped.transform("mean").to_numpy()
        count = grouped.transform("size").to_numpy()
        var = grouped.transform("var").to_numpy()
        if sd is None:
            sd = validation.noise_sd
        sds = np.where(count > 1, np.sqrt(np.nan_to_num(var)), np.nan)
        if sd is not None:
            sds = np.where(np.isnan(sds), sd, sds)
        if np.any(np.isnan(sds)):
            raise ValueError("validation data: no noise sd for rows without replicates")
        return mean, sds
    if sd is None:
        raise ValueError(
            "validation data carry no noise sd: give noise_sd= (e.g. the calibrated sigma_obs)"
        )
    return validation.y.copy(), np.full(validation.n, float(sd))


def reliability(
    predictions: az.InferenceData | xr.DataArray,
    validation: CalibrationData,
    tolerance: float,
    *,
    noise_sd: float | None = None,
    weights: Sequence[float] | None = None,
    var_name: str = "y_model",
) -> Reliability:
    """Reliability metric r(x) and its weighted mean μ_r (paper Eqs. 19–22).

    Parameters
    ----------
    predictions : InferenceData or DataArray
        Posterior draws of ``y_m = G + δ`` at the validation inputs, dims
        ``(chain, draw, pred)`` (the ``predictions`` group of :func:`kohpymc.predict`).
    validation : CalibrationData
        Validation measurements, one row per ``pred`` entry.
    tolerance : float
        ε > 0, in output units.
    noise_sd : float, optional
        σ_obs of y_D; default the validation data's ``noise_sd``.  Rows with replicates
        use the replicates' own mean and sd.
    weights : sequence of float, optional
        ``w_i`` of Eq. 22 (e.g. proportional to the input density); default uniform.
    var_name : str
        Prediction variable to use.

    Returns
    -------
    Reliability

    Examples
    --------
    >>> import numpy as np, xarray as xr
    >>> from kohpymc import CalibrationData
    >>> draws = xr.DataArray(np.zeros((1, 4, 2)), dims=("chain", "draw", "pred"))
    >>> val = CalibrationData({"x": [0.0, 1.0]}, [0.0, 0.0], noise_sd=1.0)
    >>> round(reliability(draws, val, tolerance=1.0).mu_r, 4)  # P(|N(0,1)| < 1)
    0.6827
    """
    if not np.isfinite(tolerance) or tolerance <= 0:
        raise ValueError(f"tolerance must be a positive number, got {tolerance}")
    if isinstance(predictions, az.InferenceData):
        if "predictions" not in predictions.groups():
            raise KeyError("InferenceData has no 'predictions' group (see kohpymc.predict)")
        da = predictions.predictions[var_name]
    else:
        da = predictions
    if "pred" not in da.dims:
        raise ValueError(f"predictions need a 'pred' dimension, got dims {da.dims}")
    if da.sizes["pred"] != validation.n:
        raise ValueError(f"{da.sizes['pred']} predicted points but {validation.n} validation rows")
    mean, sd = _measurement_model(validation, noise_sd)
    ym = da.transpose("chain", "draw", "pred").values
    prob = ndtr((ym + tolerance - mean) / sd) - ndtr((ym - tolerance - mean) / sd)
    w = np.ones(validation.n) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (validation.n,) or np.any(w < 0) or not np.any(w > 0):
        raise ValueError("weights must be non-negative, one per validation row, not all zero")
    w = w / w.sum()
    per_draw = prob @ w  # (chain, draw)
    mu_r = float(per_draw.mean())
    mcse = float(np.ravel(az.mcse(per_draw))[0]) if per_draw.shape[1] > 3 else float("nan")
    pointwise = xr.DataArray(
        prob.mean(axis=(0, 1)),
        dims=("pred",),
        coords={k: v for k, v in da.coords.items() if v.dims == ("pred",)},
        name="reliability",
    )
    return Reliability(pointwise=pointwise, mu_r=mu_r, mcse=mcse, tolerance=float(tolerance))
