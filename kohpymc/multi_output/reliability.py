r"""Reliability of a joint calibration: per output and combined (paper Eqs. 19–22).

Output ``k`` is scored on its own validation rows with its own tolerance ε_k and its
own σ of y_D (the validation or calibration data's known/pooled σ_obs,k, else the
posterior draws of ``<k>::sigma_obs``, draw by draw), exactly as a single-output
calibration is (:func:`kohpymc.reliability`):

.. math::

    p_{k,i,s} = \Phi\Big(\frac{y^s_{m,k}(x_i) + \epsilon_k - D_{k,i}}{\sigma_k}\Big)
              - \Phi\Big(\frac{y^s_{m,k}(x_i) - \epsilon_k - D_{k,i}}{\sigma_k}\Big),
    \qquad r_k(x_i) = \frac1S \sum_s p_{k,i,s}.

**Combined reliability.**  With ``combine="rows"`` (default) every validation row of
every output counts once, Eq. 22 on the stacked validation set:

.. math::

    \mu_r^{comb} = \frac{\sum_k \sum_i r_k(x_i)}{\sum_k n_k};

with ``combine="outputs"`` every output counts once, :math:`\frac1K \sum_k \mu_{r,k}`.

**Weights** (Eq. 22, ``weights``: per output, e.g. proportional to the input density):
output ``k``'s :math:`\mu_{r,k} = \sum_i w_{k,i} r_k(x_i) / \sum_i w_{k,i}`, and the
combined row over all rows is :math:`\sum_k \sum_i w_{k,i} r_k(x_i) / \sum_k \sum_i
w_{k,i}` (an output without weights has :math:`w_{k,i} = 1`; with none at all this is
the formula above).
Either is a mean of per-row probabilities, so it lies in [0, 1] and between the
smallest and the largest per-output μ_r.  Its Monte-Carlo standard error comes from the
per-draw averages :math:`q_s` (whose mean is the combined μ_r), as for one output.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr
from scipy.special import ndtr

from kohpymc.checks import check_tolerance
from kohpymc.multi_output.calibration import MultiOutputCalibration, predict_output
from kohpymc.multi_output.data import MultiOutputData, per_output
from kohpymc.validation import _measurement_model, row_weights, validation_noise
from kohpymc.warning_filters import single_chain_notes_hidden

__all__ = ["OutputReliability", "output_reliability", "reliability_table", "COMBINED"]

#: index label of the combined row of the table
COMBINED = "combined"


@dataclass
class OutputReliability:
    """Per-output and combined reliability of a joint calibration.

    Attributes
    ----------
    table : pandas.DataFrame
        One row per output and a last row ``"combined"``; columns ``n``,
        ``tolerance``, ``mu_r``, ``mu_r_mcse``, ``noise`` (where σ of y_D came from).
    pointwise : dict of str to xarray.DataArray
        ``r_k(x_i)`` per output over ``pred`` (input values as coordinates).
    combine : str
        ``"rows"`` or ``"outputs"`` (see the module docstring).
    """

    table: pd.DataFrame
    pointwise: dict[str, xr.DataArray]
    combine: str


def _probabilities(ym: np.ndarray, D: np.ndarray, sd: Any, tolerance: float) -> np.ndarray:
    """``p[chain, draw, row]`` of Eq. 19 integrated exactly over y_D ~ N(D, sd²)."""
    return ndtr((ym + tolerance - D) / sd) - ndtr((ym - tolerance - D) / sd)


def _mcse(per_draw: np.ndarray) -> float:
    with single_chain_notes_hidden():
        return float(np.ravel(az.mcse(per_draw))[0]) if per_draw.shape[1] > 3 else float("nan")


def output_reliability(
    calibration: MultiOutputCalibration,
    validation: MultiOutputData,
    tolerance: float | Mapping[str, float],
    *,
    predictions: Mapping[str, az.InferenceData] | None = None,
    combine: Literal["rows", "outputs"] = "rows",
    weights: Mapping[str, Any] | None = None,
    random_seed: int | None = None,
) -> OutputReliability:
    """Reliability r(x) per output and combined for a joint calibration.

    Parameters
    ----------
    calibration : MultiOutputCalibration
    validation : MultiOutputData
        Validation rows per output (outputs it lacks are not scored).
    tolerance : float or mapping output -> float
        ε_k in each output's units (a mapping is needed when units differ).
    predictions : mapping output -> InferenceData, optional
        :func:`~kohpymc.multi_output.calibration.predict_output` at the validation
        inputs; default: predicted here (seeded with ``random_seed``).
    combine : {"rows", "outputs"}
        Weight of the combined row: every validation row once, or every output once.
    weights : mapping output -> sequence of float, optional
        ``w_{k,i}`` of Eq. 22 per validation row of an output (outputs left out:
        uniform, 1 per row); see the module docstring for the combined row.

    Returns
    -------
    OutputReliability

    Examples
    --------
    >>> rel = output_reliability(cal, val, {"u": 0.75, "strain": 7.5})  # doctest: +SKIP
    >>> rel.table.index.tolist()  # doctest: +SKIP
    ['u', 'strain', 'combined']
    """
    outputs = _scored_outputs(calibration, validation, combine)
    tolerances = per_output(tolerance, validation.outputs, "tolerance")
    given = per_output(weights or {}, validation.outputs, "weights")
    rows, pointwise, per_draw, shares = [], {}, [], []
    for k in outputs:
        if tolerances[k] is None:
            raise KeyError(f"tolerance gives no value for output {k!r}")
        eps = check_tolerance(tolerances[k])
        val = validation[k]
        pred = (predictions or {}).get(k)
        if pred is None:
            pred = predict_output(calibration, k, val, random_seed=random_seed)
        w = np.ones(val.n) if given[k] is None else np.asarray(given[k], dtype=float)
        q, pointwise[k], row = _score_output(calibration, k, val, pred, eps, w)
        per_draw.append(q)
        shares.append(w.sum() if combine == "rows" else 1.0)
        rows.append(row)
    n = sum(validation[k].n for k in outputs)
    rows.append(_combined_row(per_draw, shares, n, combine))
    table = pd.DataFrame(rows).set_index("output")
    return OutputReliability(table, pointwise, combine)


def _scored_outputs(
    calibration: MultiOutputCalibration, validation: MultiOutputData, combine: str
) -> list[str]:
    """The calibrated outputs that have validation rows (checks ``combine``)."""
    if combine not in ("rows", "outputs"):
        raise ValueError(f"combine must be 'rows' or 'outputs', got {combine!r}")
    outputs = [k for k in calibration.outputs if k in validation.outputs]
    if not outputs:
        raise ValueError(
            f"validation outputs {list(validation.outputs)} share none with the calibrated "
            f"outputs {list(calibration.outputs)}"
        )
    return outputs


def _score_output(
    calibration: MultiOutputCalibration, k: str, val: Any, pred: Any, eps: float, w: np.ndarray
) -> tuple[np.ndarray, xr.DataArray, dict[str, Any]]:
    """Output ``k``'s per-draw weighted mean probabilities, its r(x) and its table row."""
    da = pred.predictions["y_model"]  # arviz adds groups at run time
    ym = da.transpose("chain", "draw", "pred").values
    if ym.shape[-1] != val.n:
        raise ValueError(f"output {k!r}: {ym.shape[-1]} predictions for {val.n} rows")
    sigma = calibration.sigma_obs_draws(k)
    posterior = None if sigma is None else xr.Dataset({"sigma_obs": sigma})
    noise = validation_noise(
        val, calibration.data[k], posterior, calibration.built.parts[k].formulation
    )
    D, sd = _measurement_model(val, noise, ym.shape)
    prob = _probabilities(ym, D, sd, eps)
    try:
        q = prob @ row_weights(w, val.n)
    except ValueError as err:
        raise ValueError(f"output {k!r}: {err}") from err
    pointwise = xr.DataArray(
        prob.mean(axis=(0, 1)),
        dims=("pred",),
        coords={c: v for c, v in da.coords.items() if v.dims == ("pred",)},
        name=f"reliability_{k}",
    )
    row = {"output": k, "n": val.n, "tolerance": eps, "mu_r": float(q.mean()),
           "mu_r_mcse": _mcse(q), "noise": noise.describe()}  # fmt: skip
    return q, pointwise, row


def _combined_row(
    per_draw: list[np.ndarray], weights: list[float], n: int, combine: str
) -> dict[str, Any]:
    """The table's combined row: the weighted mean of the outputs' per-draw means."""
    w = np.asarray(weights, dtype=float) / np.sum(weights)
    q_comb = sum(wk * qk for wk, qk in zip(w, per_draw, strict=True))
    return {"output": COMBINED, "n": n, "tolerance": np.nan,
            "mu_r": float(q_comb.mean()), "mu_r_mcse": _mcse(q_comb),
            "noise": f"mean over {'all rows' if combine == 'rows' else 'outputs'}"}  # fmt: skip


def reliability_table(
    calibration: MultiOutputCalibration,
    validation: MultiOutputData,
    tolerance: float | Mapping[str, float],
    **options: Any,
) -> pd.DataFrame:
    """The table of :func:`output_reliability`: one row per output plus ``"combined"``.

    Examples
    --------
    >>> reliability_table(cal, val, {"u": 0.75, "strain": 7.5}).index.tolist()  # doctest: +SKIP
    ['u', 'strain', 'combined']
    """
    return output_reliability(calibration, validation, tolerance, **options).table
