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

so only the posterior draws are Monte Carlo, with no second layer of sampling.  σ is
the same for every formulation when one exists apart from them (known, or pooled from
replicates with Eq. 28, :func:`shared_validation_noise`); otherwise each draw ``s`` uses
its own posterior draw σ_obs^s (:func:`validation_noise`), never a plugged-in posterior
mean.  The
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
import xarray as xr
from scipy.special import ndtr

from kohpymc.calibration import Calibration, calibrate, predict
from kohpymc.checks import check_tolerance
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import SamplerTroubleWarning
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.physics import PhysicsModel
from kohpymc.warning_filters import single_chain_notes_hidden

__all__ = [
    "Reliability",
    "reliability",
    "ValidationNoise",
    "describe_noise",
    "shared_validation_noise",
    "validation_noise",
    "validation_metrics",
    "predictive_scores",
    "fit_and_score",
    "score_calibration",
    "Scored",
    "derived_seed",
    "row_weights",
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


@dataclass(frozen=True)
class ValidationNoise:
    """The σ of y_D in the reliability integral, and where it came from.

    Attributes
    ----------
    sd : float or xarray.DataArray
        One value for every draw, or one per posterior draw (dims ``chain, draw``).
    source : str
        Where σ came from, in words (``"validation noise_sd"``, ``"pooled from the
        validation replicates (Eq. 28)"``, ``"posterior draws of sigma_obs"`` ...).
    note : str
        Anything a reader should know (e.g. that only a sum of variances is identified).

    Examples
    --------
    >>> ValidationNoise(0.3, "validation noise_sd").to_dict()["sd"]
    0.3
    """

    sd: float | xr.DataArray
    source: str
    note: str = ""

    @property
    def per_draw(self) -> bool:
        """True when σ varies over the posterior draws."""
        return isinstance(self.sd, xr.DataArray)

    def to_dict(self) -> dict[str, Any]:
        """Plain values for a table or ``study.json``: source, σ (its mean over draws)."""
        out: dict[str, Any] = {"source": self.source, "per_draw": self.per_draw}
        if isinstance(self.sd, xr.DataArray):
            values = np.asarray(self.sd.values, dtype=float)
            out.update(sd=float(values.mean()), sd_of_draws=float(values.std()))
        else:
            out["sd"] = float(self.sd)
        if self.note:
            out["note"] = self.note
        return out

    def describe(self) -> str:
        """One short line, e.g. ``"0.3 (validation noise_sd)"``."""
        return describe_noise(self.to_dict())


def describe_noise(described: dict[str, Any]) -> str:
    """One line from :meth:`ValidationNoise.to_dict`'s values.

    Examples
    --------
    >>> describe_noise({"source": "posterior draws of sigma_obs", "sd": 0.52, "per_draw": True})
    'posterior draws of sigma_obs (mean 0.52)'
    """
    sd, source = described.get("sd"), described.get("source", "?")
    if sd is None:
        return str(source)
    if described.get("per_draw"):
        return f"{source} (mean {float(sd):.4g})"
    return f"{float(sd):.4g} ({source})"


def shared_validation_noise(
    validation: CalibrationData, calibration: CalibrationData
) -> ValidationNoise | None:
    """σ of y_D that does not depend on the formulation, when one exists.

    In this order: the validation data's known noise sd; the sd pooled from the
    validation replicates (Eq. 28); the calibration data's known or pooled sd.  ``None``
    when the noise is unknown (it is then calibrated, and each formulation scores with
    its own draws of σ_obs: :func:`validation_noise`).  Preferring a shared σ is the
    paper's advice (Section 6.2): otherwise every formulation is scored against a
    different y_D.

    Examples
    --------
    >>> from kohpymc import CalibrationData
    >>> val = CalibrationData({"x": [0.0]}, [1.0])
    >>> shared_validation_noise(val, CalibrationData({"x": [0.0]}, [1.0], noise_sd=0.2)).sd
    0.2
    >>> shared_validation_noise(val, CalibrationData({"x": [0.0]}, [1.0])) is None
    True
    """
    for data, which in ((validation, "validation"), (calibration, "calibration")):
        if data.noise_sd is None:
            continue
        if data.noise_sd_estimated:
            return ValidationNoise(data.noise_sd, f"pooled from the {which} replicates (Eq. 28)")
        return ValidationNoise(data.noise_sd, f"{which} noise_sd")
    return None


def validation_noise(
    validation: CalibrationData,
    calibration: CalibrationData,
    posterior: Any = None,
    formulation: Discrepancy | None = None,
) -> ValidationNoise:
    """σ of y_D for one formulation: the shared one, else its posterior draws of σ_obs.

    Parameters
    ----------
    validation, calibration : CalibrationData
    posterior : xarray.Dataset, optional
        The formulation's posterior; its ``sigma_obs`` draws are used draw by draw when
        no shared σ exists (:func:`shared_validation_noise`).
    formulation : Discrepancy, optional
        Says when σ_obs is identified only together with a discrepancy variance
        (:meth:`Discrepancy.noise_partner`); the note then says so.

    Raises
    ------
    ValueError
        When neither a shared σ nor ``sigma_obs`` draws exist.

    Examples
    --------
    >>> import numpy as np, xarray as xr
    >>> from kohpymc import CalibrationData
    >>> post = xr.Dataset({"sigma_obs": (("chain", "draw"), np.full((1, 3), 0.4))})
    >>> val = CalibrationData({"x": [0.0]}, [1.0])
    >>> validation_noise(val, val, post).describe()
    'posterior draws of sigma_obs (mean 0.4)'
    """
    shared = shared_validation_noise(validation, calibration)
    if shared is not None:
        return shared
    if posterior is None or "sigma_obs" not in posterior:
        raise ValueError(
            "no noise sd for the validation data: the data carry none and the posterior "
            "has no sigma_obs (give noise_sd for the validation or calibration data)"
        )
    note = ""
    partner = formulation.noise_partner() if formulation is not None else None
    if partner is not None:
        name, kind = partner
        what = f"sigma_obs² + {name}²" if kind == "sd" else f"sigma_obs² + exp({name}[0])"
        note = (
            f"with unknown noise only {what} is identified; y_model carries a fresh draw of "
            f"the discrepancy, so r(x) depends on the draws only through that sum"
        )
    return ValidationNoise(posterior["sigma_obs"], "posterior draws of sigma_obs", note)


def _measurement_model(
    validation: CalibrationData, noise: float | ValidationNoise | xr.DataArray | None, shape
) -> tuple[np.ndarray, np.ndarray]:
    """D and σ of y_D, broadcastable against draws of shape ``(chain, draw, pred)``.

    Every row is its own measurement D (rows with replicates too); σ is the pooled
    replicate sd (Eq. 28) for replicated validation data, never each group's own sd.
    """
    if isinstance(noise, ValidationNoise):
        noise = noise.sd
    if noise is None:
        noise = validation.noise_sd
    if noise is None:
        raise ValueError(
            "validation data carry no noise sd: give noise_sd= (e.g. the calibrated "
            "sigma_obs draws, see kohpymc.validation.validation_noise)"
        )
    if isinstance(noise, xr.DataArray):
        if set(noise.dims) != {"chain", "draw"}:
            raise ValueError(f"per-draw noise sd needs dims (chain, draw), got {noise.dims}")
        sd = np.asarray(noise.transpose("chain", "draw").values, dtype=float)
        if sd.shape != tuple(shape[:2]):
            raise ValueError(
                f"per-draw noise sd has {sd.shape} (chain, draw) but the predictions "
                f"have {tuple(shape[:2])}"
            )
        sd = sd[..., None]
    else:
        sd = np.asarray(float(noise))
    if not (np.all(np.isfinite(sd)) and np.all(sd > 0)):
        raise ValueError("noise sd of the validation data must be positive and finite")
    return validation.y.copy(), sd


def _mcse_of_mean(per_draw: np.ndarray) -> float:
    """Monte Carlo standard error of the mean of ``(chain, draw)`` values.

    NaN with three draws per chain or fewer; 0 when every draw has the same value.  The
    values are centred first: the MCSE of a mean does not depend on a shift, and ArviZ's
    variance of values such as 1 - 1e-11 ± 1e-12 loses every digit (it came out negative:
    a NaN and a numpy warning).
    """
    if per_draw.shape[1] <= 3:
        return float("nan")
    centred = per_draw - per_draw.mean()
    if not centred.any():
        return 0.0
    with single_chain_notes_hidden():
        return float(np.ravel(az.mcse(centred))[0])


def reliability(
    predictions: Calibration | az.InferenceData | xr.DataArray,
    validation: CalibrationData,
    tolerance: float,
    *,
    noise_sd: float | ValidationNoise | xr.DataArray | None = None,
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
    noise_sd : float, ValidationNoise or DataArray, optional
        σ of y_D: one value, or one per posterior draw (a DataArray over ``chain, draw``
        matching the predictions, e.g. the ``sigma_obs`` draws; draw ``s`` of y_m is then
        scored with σ^s).  Default the validation data's ``noise_sd`` (for replicated
        validation data the pooled sd of Eq. 28; each row is its own measurement D).
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
    ym = da.transpose("chain", "draw", "pred").values
    mean, sd = _measurement_model(validation, noise_sd, ym.shape)
    prob = ndtr((ym + tolerance - mean) / sd) - ndtr((ym - tolerance - mean) / sd)
    per_draw = prob @ row_weights(weights, validation.n)  # (chain, draw)
    mu_r = float(per_draw.mean())
    mcse = _mcse_of_mean(per_draw)
    pointwise = xr.DataArray(
        prob.mean(axis=(0, 1)),
        dims=("pred",),
        coords={k: v for k, v in da.coords.items() if v.dims == ("pred",)},
        name="reliability",
    )
    return Reliability(pointwise=pointwise, mu_r=mu_r, mcse=mcse, tolerance=float(tolerance))


def row_weights(weights: Sequence[float] | np.ndarray | None, n: int) -> np.ndarray:
    """``w_i / Σ w`` of Eq. 22 for ``n`` validation rows (uniform when ``weights`` is None).

    Examples
    --------
    >>> row_weights([1.0, 3.0], 2)
    array([0.25, 0.75])
    """
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (n,) or np.any(w < 0) or not np.any(w > 0):
        raise ValueError("weights must be non-negative, one per validation row, not all zero")
    return w / w.sum()


def predictive_scores(pred: az.InferenceData, validation: CalibrationData) -> dict[str, float]:
    """RMSE of the posterior-mean ``y_model`` and 90 % coverage of ``y_pred``.

    Neither needs the noise sd of the validation data: ``y_pred`` carries each draw's
    own measurement noise.

    Examples
    --------
    >>> import arviz as az, numpy as np
    >>> from kohpymc import CalibrationData
    >>> draws = np.random.default_rng(0).normal(0.0, 1.0, size=(1, 400, 2))
    >>> pred = az.from_dict(predictions={"y_model": 0 * draws, "y_pred": draws},
    ...                     dims={"y_model": ["pred"], "y_pred": ["pred"]})
    >>> predictive_scores(pred, CalibrationData({"x": [0.0, 1.0]}, [0.5, 3.0]))["coverage90"]
    0.5
    """
    ym = pred.predictions["y_model"].transpose(..., "pred").values
    yp = pred.predictions["y_pred"].transpose(..., "pred").values
    ym = ym.reshape(-1, ym.shape[-1])
    yp = yp.reshape(-1, yp.shape[-1])
    lo, hi = np.quantile(yp, [0.05, 0.95], axis=0)
    return {
        "rmse": float(np.sqrt(np.mean((ym.mean(axis=0) - validation.y) ** 2))),
        "coverage90": float(np.mean((validation.y >= lo) & (validation.y <= hi))),
    }


def validation_metrics(
    pred: az.InferenceData,
    validation: CalibrationData,
    tolerance: float,
    noise_sd: float | ValidationNoise | xr.DataArray | None,
    weights: Sequence[float] | None,
) -> tuple[dict[str, float], xr.Dataset]:
    """μ_r ± MCSE (:func:`reliability`) and :func:`predictive_scores`.

    Returns the scores and a Dataset (``reliability``, ``y_validation`` over ``pred``) for
    the ``predictions_constant_data`` group.

    Examples
    --------
    >>> scores, const = validation_metrics(pred, val, 0.75, 0.3, None)  # doctest: +SKIP
    >>> sorted(scores)  # doctest: +SKIP
    ['coverage90', 'mu_r', 'mu_r_mcse', 'rmse']
    """
    rel = reliability(pred, validation, tolerance, noise_sd=noise_sd, weights=weights)
    metrics = {"mu_r": rel.mu_r, "mu_r_mcse": rel.mcse, **predictive_scores(pred, validation)}
    const = rel.to_dataset()
    const["y_validation"] = xr.DataArray(validation.y, dims=("pred",))
    return metrics, const


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
        Pointwise reliability and the validation measurements (``pred`` dim); its
        attributes say which σ of y_D was used (``noise_source``, ``noise_sd``, ...).
    noise : dict
        The σ of y_D used in the reliability integral (:meth:`ValidationNoise.to_dict`).
    """

    calibration: Calibration
    predictions: az.InferenceData
    scores: dict[str, float]
    constant: xr.Dataset
    noise: dict[str, Any]

    def combined_idata(self) -> az.InferenceData:
        """The calibration's InferenceData with predictions and validation groups added."""
        idata = self.calibration.idata.copy()
        idata.extend(self.predictions)
        idata.add_groups(predictions_constant_data=self.constant)
        idata.attrs.update({k: float(v) for k, v in self.scores.items()})
        return idata


def score_calibration(
    cal: Calibration,
    validation: CalibrationData,
    *,
    tolerance: float,
    validation_weights: Sequence[float] | None = None,
    random_seed: int | None = None,
    label: str | None = None,
) -> Scored:
    """Predict a calibration at the validation inputs and score it (Eqs. 19–22).

    σ of y_D comes from :func:`validation_noise` (shared when one exists, else this
    calibration's σ_obs draws, draw by draw).  The prediction seed derives from
    ``random_seed`` and ``label`` (:func:`derived_seed`).

    Examples
    --------
    >>> scored = score_calibration(cal, validation, tolerance=0.75)  # doctest: +SKIP
    >>> scored.noise["source"]  # doctest: +SKIP
    'validation noise_sd'
    """
    label = label or cal.label
    pred = predict(cal, validation, random_seed=derived_seed(random_seed, label, 1))
    noise = validation_noise(validation, cal.data, cal.idata.posterior, cal.formulation)
    scores, const = validation_metrics(pred, validation, tolerance, noise, validation_weights)
    described = noise.to_dict()
    # NetCDF attributes hold no booleans: per_draw as 0/1
    const.attrs.update({f"noise_{k}": _attr(v) for k, v in described.items()})
    return Scored(cal, pred, scores, const, described)


def _attr(value: Any) -> Any:
    return int(value) if isinstance(value, bool) else value


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
    ``random_seed`` and ``label`` (:func:`derived_seed`); scoring is
    :func:`score_calibration`.

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
    return score_calibration(
        cal,
        validation,
        tolerance=tolerance,
        validation_weights=validation_weights,
        random_seed=random_seed,
        label=label,
    )
