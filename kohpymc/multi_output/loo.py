r"""Leave-one-out per output and combined for joint calibrations of several outputs.

PyMC's ``log_likelihood`` group holds one value per draw for an output whose rows are
not independent given the model's variables (a marginalised mean, a GP, the joint
:class:`~kohpymc.multi_output.Coregionalized` GP): PSIS-LOO would see a single
observation.  :func:`add_pointwise_log_likelihood` replaces it, as a single-output
calibration does (:mod:`kohpymc.loo`), by the exact Gaussian leave-one-out conditionals
``log p(y_k,i | y_-(k,i), φ)`` per draw:

* independent outputs: from output ``k``'s own mean and covariance.  The outputs are
  independent given θ and their own parameters, so leaving one row of output ``k`` out
  of the joint data gives the same conditional;
* the joint GP: from the joint covariance over all outputs' rows, then split by output.

Each output's values are ``<k>::y`` over ``obs_<k>``.  :func:`output_loo` compares
formulations per output (``az.compare`` on ``<k>::y``) and combined (on all outputs'
rows together, each an observation of the joint model).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import arviz as az
import numpy as np
import pandas as pd
import xarray as xr

from kohpymc.combination import loo_weights
from kohpymc.discrepancy.base import Likelihood
from kohpymc.loo import loo_log_likelihood
from kohpymc.model import CalibrationModel
from kohpymc.multi_output.model import MultiOutputModel, obs_dim, variable

__all__ = ["add_pointwise_log_likelihood", "output_loo", "COMBINED_LOO"]

#: the log-likelihood variable of all outputs' rows together (in :func:`output_loo`)
COMBINED_LOO = "all_outputs"


def _conditionals(idata: az.InferenceData, built: Any, record: Likelihood, name: str) -> Any:
    """Exact LOO conditionals of one Gaussian record of the joint model (values per draw)."""
    part = CalibrationModel(built.model, replace(record, observed=name), None, (), ())  # type: ignore[arg-type]
    return loo_log_likelihood(idata["posterior"], part)[name].values


def add_pointwise_log_likelihood(idata: az.InferenceData, built: MultiOutputModel) -> None:
    """Make every output's ``<k>::y`` in ``idata.log_likelihood`` pointwise (in place).

    Outputs whose rows PyMC already scores one by one are left as they are; the others
    get their exact Gaussian leave-one-out conditionals (see the module docstring), and
    the group's ``attrs["pointwise"]`` says ``"loo_conditional"``.  An output whose
    formulation gives no covariance keeps its per-draw value (:func:`output_loo` then
    names it).

    Examples
    --------
    >>> add_pointwise_log_likelihood(cal.idata, cal.built)  # doctest: +SKIP
    >>> cal.idata["log_likelihood"]["u::y"].dims  # doctest: +SKIP
    ('chain', 'draw', 'obs_u')
    """
    group = idata["log_likelihood"]
    coords = {"chain": group["chain"].values, "draw": group["draw"].values}
    values: dict[str, Any] = {}
    if built.joint is not None:
        joint_record = Likelihood(None, built.joint.mean, built.joint.covariance)  # type: ignore[arg-type]
        joint = _conditionals(idata, built, joint_record, "y")
        for j, k in enumerate(built.outputs):
            values[k] = joint[..., built.joint.output_index == j]
    else:
        for k, part in built.parts.items():
            name = built.observed_name(k)
            record = part.likelihood
            if record is None or (name in group and group[name].ndim == 3):
                continue
            if record.pointwise is not None or record.covariance is None:
                continue
            values[k] = _conditionals(idata, built, record, name)
    if not values:
        return
    ds = group.drop_vars([variable(k, "y") for k in values if variable(k, "y") in group])
    for k, v in values.items():
        ds[variable(k, "y")] = xr.DataArray(v, dims=("chain", "draw", obs_dim(k)), coords=coords)
    ds.attrs["pointwise"] = "loo_conditional"
    # setattr, not idata[...] = : item assignment lists the group twice (arviz 0.23)
    setattr(idata, "log_likelihood", ds)  # noqa: B010 - arviz adds groups at run time


def output_loo(
    results: Mapping[str, az.InferenceData], outputs: tuple[str, ...] | list[str]
) -> pd.DataFrame:
    """LOO comparison of formulations per output and combined (stacking weights).

    Parameters
    ----------
    results : mapping label -> InferenceData
        Joint calibrations with pointwise ``<k>::y`` (:func:`add_pointwise_log_likelihood`).
    outputs : sequence of str

    Returns
    -------
    pandas.DataFrame
        Indexed by ``(formulation, output)`` with ``output`` one of ``outputs`` or
        ``"combined"`` (all outputs' rows as one data set): ``elpd_loo``,
        ``loo_weight`` (stacking, summing to 1 over formulations per output) and
        ``max_pareto_k``.

    Examples
    --------
    >>> output_loo({"M0": cal0.idata, "M1": cal1.idata}, ["u", "strain"])  # doctest: +SKIP
    """
    tables = {}
    for k in outputs:
        var = variable(k, "y")
        tables[k] = _compare({label: _only(idata, var) for label, idata in results.items()}, var)
    stacked = {label: _all_rows(idata, outputs) for label, idata in results.items()}
    tables["combined"] = _compare(stacked, COMBINED_LOO)
    frames = [
        table[["elpd_loo", "weight", "max_pareto_k"]]
        .rename(columns={"weight": "loo_weight"})
        .assign(output=k)
        .rename_axis("formulation")
        .reset_index()
        for k, table in tables.items()
    ]
    return pd.concat(frames).set_index(["formulation", "output"])


def _compare(results: dict[str, az.InferenceData], var: str) -> pd.DataFrame:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ArviZ's Pareto-k notes: the table has max_pareto_k
        return loo_weights(results, var_name=var)


def _only(idata: az.InferenceData, var: str) -> az.InferenceData:
    """The posterior with one log-likelihood variable (``az.loo`` needs exactly one)."""
    own = idata["log_likelihood"][[var]]
    return az.InferenceData(posterior=idata["posterior"], log_likelihood=own)


def _all_rows(idata: az.InferenceData, outputs: Any) -> az.InferenceData:
    """Every output's pointwise values as one variable over one observation dimension."""
    parts = []
    for k in outputs:
        da = idata["log_likelihood"][variable(k, "y")]
        if da.ndim != 3:
            raise ValueError(f"log-likelihood of output {k!r} is not pointwise")
        parts.append(da.transpose("chain", "draw", ...).values)
    posterior = idata["posterior"]
    stacked = xr.Dataset(
        {COMBINED_LOO: (("chain", "draw", "obs_all"), np.concatenate(parts, axis=-1))},
        coords={"chain": posterior["chain"].values, "draw": posterior["draw"].values},
    )
    return az.InferenceData(posterior=posterior, log_likelihood=stacked)
