"""Posterior predictive draws for every posterior draw in one numpy evaluation.

:func:`pymc.sample_posterior_predictive` compiles the forward graph with PyTensor's C
backend (from an empty cache, g++ builds ~5 modules per beam formulation, ~10 s for the
beam study) and then calls it once per draw.  Here the same graph — the requested
variables with the posterior's free variables as inputs and every other random variable
drawn afresh — is vectorised over the draws (:func:`kohpymc.batched_map.rows_function`)
and run once by PyTensor's Python linker: nothing compiled, one numpy call per node.
The draws are as PyMC's in distribution, not in stream.  When the graph does not
vectorise, PyMC's own function runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import arviz as az
import numpy as np
import pymc as pm
import pytensor.tensor as pt
import xarray as xr
from pytensor.compile.sharedvalue import SharedVariable
from pytensor.graph.traversal import ancestors
from pytensor.tensor.random.op import RandomVariable

__all__ = ["sample_predictions"]


def sample_predictions(
    idata: az.InferenceData,
    model: pm.Model,
    var_names: Sequence[str],
    random_seed: int | None = None,
    progressbar: bool = False,
) -> az.InferenceData:
    """Draws of ``var_names`` given each posterior draw, as a ``predictions`` group.

    What ``pm.sample_posterior_predictive(idata, var_names=var_names,
    predictions=True)`` returns (dims and coords from ``model``), batched over the draws
    when the graph vectorises; else PyMC's function runs.

    Examples
    --------
    >>> import pymc as pm, xarray as xr
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu")
    ...     _ = pm.Normal("y", mu, 1e-6, shape=2)
    >>> post = xr.Dataset({"mu": (("chain", "draw"), [[0.0, 5.0]])})
    >>> pred = sample_predictions(az.InferenceData(posterior=post), model, ["y"], 1)
    >>> (np.round(pred.predictions["y"].values, 3) + 0.0).tolist()  # no -0.0
    [[[0.0, 0.0], [5.0, 5.0]]]
    """
    batched = _batched(idata["posterior"], model, list(var_names), random_seed)
    if batched is not None:
        return batched
    with model:
        return pm.sample_posterior_predictive(
            idata, var_names=list(var_names), predictions=True, random_seed=random_seed,
            progressbar=progressbar,
        )  # fmt: skip


def _batched(
    posterior: xr.Dataset, model: pm.Model, var_names: list[str], random_seed: int | None
) -> az.InferenceData | None:
    """:func:`sample_predictions` in one evaluation, or ``None`` when it does not vectorise.

    The posterior's free variables (those not requested) are the inputs; a random
    variable that depends on none of them would be drawn once for all draws, so such a
    graph is left to PyMC.
    """
    from pymc.backends.arviz import coords_and_dims_for_inferencedata, dict_to_dataset
    from pymc.pytensorf import join_nonshared_inputs, reseed_rngs

    from kohpymc.batched_map import _slow_to_vectorize, rows_function

    requested = [model[name] for name in var_names]
    if _slow_to_vectorize(requested):  # before cloning the graph (a GP's: seconds)
        return None
    given = [rv for rv in model.free_RVs if rv.name in posterior and rv.name not in var_names]
    values = [posterior[rv.name].transpose("chain", "draw", ...).values for rv in given]
    point = {rv.name: v[0, 0] for rv, v in zip(given, values, strict=True)}
    outputs, flat = join_nonshared_inputs(
        point=point, outputs=requested, inputs=given,
        make_inputs_shared=False,
    )  # fmt: skip
    if _undrawn_per_row(outputs, flat):
        return None
    outputs = _sized_draws_batched(outputs, flat)
    try:
        function = rows_function(flat, outputs, optimizer="None")  # one evaluation: no rewrites
    except ValueError:  # a random variable's size that PyTensor cannot extend
        return None
    if function is None:
        return None
    rngs = [v for v in ancestors(outputs) if isinstance(v, SharedVariable) and _is_rng(v)]
    if random_seed is not None:
        reseed_rngs(rngs, random_seed)
    n_chain, n_draw = posterior.sizes["chain"], posterior.sizes["draw"]
    rows = np.concatenate([v.reshape(n_chain * n_draw, -1) for v in values], axis=1)
    out = {
        name: np.asarray(value).reshape(n_chain, n_draw, *np.shape(value)[1:])
        for name, value in zip(var_names, function(rows), strict=True)
    }
    coords, dims = coords_and_dims_for_inferencedata(model)
    coords = {**coords, "chain": posterior["chain"].values, "draw": posterior["draw"].values}
    dataset = dict_to_dataset(
        out, library=pm, dims=dims, coords=coords, default_dims=["chain", "draw"]
    )
    return az.InferenceData(predictions=dataset)


def _is_rng(variable: Any) -> bool:
    return type(variable.type).__name__ == "RandomGeneratorType"


def _sized_draws_batched(outputs: Sequence[Any], flat: Any) -> list[Any]:
    """``outputs`` with each sized scalar random variable's first parameter batched.

    PyTensor extends a random variable's ``size`` by the new batch dimensions of its
    *first* parameter only, so vectorising ``Normal(0, σ(θ), size=n)`` fails; here the
    first parameter becomes ``μ + 0 · σ(θ)`` (the same values: parameters of posterior
    draws are finite) when it depends on no posterior value and another one does.
    """
    from pytensor.graph.fg import FunctionGraph

    fgraph = FunctionGraph(outputs=list(outputs), clone=False, copy_inputs=False)
    for node in fgraph.toposort():
        op = node.op
        if not isinstance(op, RandomVariable) or _no_size(op.size_param(node)):
            continue
        params = op.dist_params(node)
        if any(op.ndims_params) or _depends(params[0], flat):
            continue
        batched = [p for p in params[1:] if _depends(p, flat)]
        if not batched:
            continue
        dtype = params[0].type.dtype  # type: ignore[attr-defined]  # a TensorType's
        first = pt.cast(pt.add(params[0], pt.mul(0, batched[0])), dtype)
        new = op.make_node(op.rng_param(node), op.size_param(node), first, *params[1:])
        fgraph.replace_all(list(zip(node.outputs, new.outputs, strict=True)), import_missing=True)
    return list(fgraph.outputs)


def _no_size(size: Any) -> bool:
    return type(size.type).__name__ == "NoneTypeT"


def _depends(variable: Any, flat: Any) -> bool:
    return flat in ancestors([variable])


def _undrawn_per_row(outputs: Sequence[Any], flat: Any) -> bool:
    """Whether a random variable in ``outputs`` depends on no posterior value."""
    for node in {v.owner for v in ancestors(outputs) if v.owner is not None}:
        if isinstance(node.op, RandomVariable) and flat not in ancestors(node.inputs):
            return True
    return False
