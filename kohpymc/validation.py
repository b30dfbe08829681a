r"""Validation: the reliability metric (paper Section 5.1, Eqs. 19–22) and fit-and-score.

This is the one layer that turns a calibration into validation scores, used by studies
and discovery alike: :func:`reliability`, :func:`validation_metrics` (μ_r ± MCSE, RMSE,
90 % coverage), the choice of σ for y_D (:func:`validation_noise_sd`) and
:func:`fit_and_score` (calibrate, predict at the validation inputs, score).

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

import warnings
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr
from scipy.special import ndtr

from kohpymc.calibration import Calibration, calibrate, predict
from kohpymc.checks import check_tolerance
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import SamplerTroubleWarning
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.physics import PhysicsModel

__all__ = [
    "Reliability",
    "reliability",
    "validation_metrics",
    "validation_noise_sd",
    "fit_and_score",
    "Scored",
    "derived_seed",
]


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
    predictions: Calibration | az.InferenceData | xr.DataArray,
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
    predictions : Calibration, InferenceData or DataArray
        Posterior draws of ``y_m = G + δ`` at the validation inputs, dims
        ``(chain, draw, pred)`` (the ``predictions`` group of :func:`kohpymc.predict`),
        or a :class:`~kohpymc.Calibration`, which is then predicted at the validation
        inputs (unseeded: pass predictions for reproducible draws).
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
    tolerance = check_tolerance(tolerance)
    if isinstance(predictions, Calibration):
        predictions = predict(predictions, validation)
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


def validation_metrics(
    pred: az.InferenceData,
    validation: CalibrationData,
    tolerance: float,
    noise_sd: float | None,
    weights: Sequence[float] | None,
) -> tuple[dict[str, float], xr.Dataset]:
    """μ_r ± MCSE, RMSE of the posterior-mean ``y_model`` and 90 % coverage of ``y_pred``.

    Returns the scores and a Dataset (``reliability``, ``y_validation`` over ``pred``) for
    the ``predictions_constant_data`` group.

    Examples
    --------
    >>> scores, const = validation_metrics(pred, val, 0.75, 0.3, None)  # doctest: +SKIP
    >>> sorted(scores)  # doctest: +SKIP
    ['coverage90', 'mu_r', 'mu_r_mcse', 'rmse']
    """
    rel = reliability(pred, validation, tolerance, noise_sd=noise_sd, weights=weights)
    ym = pred.predictions["y_model"].transpose(..., "pred").values
    yp = pred.predictions["y_pred"].transpose(..., "pred").values
    ym = ym.reshape(-1, ym.shape[-1])
    yp = yp.reshape(-1, yp.shape[-1])
    lo, hi = np.quantile(yp, [0.05, 0.95], axis=0)
    metrics = {
        "mu_r": rel.mu_r,
        "mu_r_mcse": rel.mcse,
        "rmse": float(np.sqrt(np.mean((ym.mean(axis=0) - validation.y) ** 2))),
        "coverage90": float(np.mean((validation.y >= lo) & (validation.y <= hi))),
    }
    const = rel.to_dataset()
    const["y_validation"] = xr.DataArray(validation.y, dims=("pred",))
    return metrics, const


def validation_noise_sd(
    validation: CalibrationData, calibration: CalibrationData, posterior: Any = None
) -> float | None:
    """σ of y_D: the validation data's, else the calibration data's, else calibrated σ_obs.

    ``posterior`` is a posterior Dataset (or anything indexable by ``"sigma_obs"``);
    its mean σ_obs is the last resort.  ``None`` when none is available.

    Examples
    --------
    >>> from kohpymc import CalibrationData
    >>> val = CalibrationData({"x": [0.0]}, [1.0])
    >>> validation_noise_sd(val, CalibrationData({"x": [0.0]}, [1.0], noise_sd=0.2))
    0.2
    """
    if validation.noise_sd is not None or validation.replicates is not None:
        return validation.noise_sd
    if calibration.noise_sd is not None:
        return calibration.noise_sd
    if posterior is not None and "sigma_obs" in posterior:
        return float(posterior["sigma_obs"].mean())
    return None


def derived_seed(random_seed: int | None, label: str, purpose: int) -> int | None:
    """A seed per (label, purpose), so adding a formulation changes no other's draws.

    Examples
    --------
    >>> derived_seed(1, "M1", 0) == derived_seed(1, "M1", 0) != derived_seed(1, "M2", 0)
    True
    """
    if random_seed is None:
        return None
    key = (zlib.crc32(label.encode()), purpose)
    return int(np.random.SeedSequence(random_seed, spawn_key=key).generate_state(1)[0])


@dataclass
class Scored:
    """A calibration with its predictions at the validation inputs and its scores.

    Attributes
    ----------
    calibration : Calibration
    predictions : arviz.InferenceData
        The ``predictions`` group at the validation inputs.
    scores : dict
        ``mu_r``, ``mu_r_mcse``, ``rmse``, ``coverage90``.
    constant : xarray.Dataset
        Pointwise reliability and the validation measurements (``pred`` dim).
    noise_sd : float or None
        The σ of y_D used in the reliability integral.
    """

    calibration: Calibration
    predictions: az.InferenceData
    scores: dict[str, float]
    constant: xr.Dataset
    noise_sd: float | None

    def combined_idata(self) -> az.InferenceData:
        """The calibration's InferenceData with predictions and validation groups added."""
        idata = self.calibration.idata.copy()
        idata.extend(self.predictions)
        idata.add_groups(predictions_constant_data=self.constant)
        idata.attrs.update({k: float(v) for k, v in self.scores.items()})
        return idata


def fit_and_score(
    physics: PhysicsModel,
    calibration: CalibrationData,
    validation: CalibrationData,
    formulation: Discrepancy | None,
    *,
    tolerance: float,
    validation_weights: Sequence[float] | None = None,
    random_seed: int | None = None,
    label: str | None = None,
    **settings: Any,
) -> Scored:
    """Calibrate one formulation, predict at the validation inputs and score it.

    Sampler trouble is recorded in the calibration's ``problems`` (not warned here: the
    caller reports it).  Seeds of the calibration and the predictions derive from
    ``random_seed`` and ``label`` (:func:`derived_seed`).

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> scored = fit_and_score(beam.physics_model(), beam.generate_data(seed=1),
    ...                        beam.generate_data((3.5,), seed=2), None, tolerance=0.75,
    ...                        random_seed=1, draws=200, chains=2)  # doctest: +SKIP
    >>> 0 <= scored.scores["mu_r"] <= 1  # doctest: +SKIP
    True
    """
    label = label or (formulation.label if formulation is not None else "M0")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SamplerTroubleWarning)
        cal = calibrate(
            physics,
            calibration,
            formulation,
            random_seed=derived_seed(random_seed, label, 0),
            **settings,
        )
    pred = predict(cal, validation, random_seed=derived_seed(random_seed, label, 1))
    noise_sd = validation_noise_sd(validation, calibration, cal.idata.posterior)
    scores, const = validation_metrics(pred, validation, tolerance, noise_sd, validation_weights)
    return Scored(cal, pred, scores, const, noise_sd)
