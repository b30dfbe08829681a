"""One replicate: simulate from the prior predictive, fit on the compiled model, score.

The fitted model is composed once and its observed values replaced by a shared variable
(:func:`swappable_observations`), so one compiled log density serves every replicate of a
process (:func:`fit_replicate` sets the shared variable and samples).  The simulation model
is the same formulation with its linear mean coefficients not integrated out (every
parameter has a drawn value), or what ``[check.simulate]`` declares; one compiled draw
function, reseeded per replicate, gives the truth and the data.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pymc as pm
import pytensor
from pytensor.tensor.variable import TensorConstant

from kohpymc.config import CheckSpec, StudySpec, load_study
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import n_divergences, rhat_limit, sampler_diagnostics
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.model import compose_model
from kohpymc.physics import PhysicsModel
from kohpymc.sampling import sample_posterior
from kohpymc.sbc.settings import CheckSettings
from kohpymc.value_space import ValueSpace, value_space

__all__ = ["Replicate", "fit_replicate", "rank_of_truth", "swappable_observations"]
# Fitter, Recipe, Simulator, build_fitter, build_simulator, verify_swap, cached_fitter and
# remember serve kohpymc.sbc.check


def swappable_observations(model: pm.Model, y: np.ndarray) -> tuple[pm.Model, Any]:
    """A copy of ``model`` whose observed values ``y`` live in one shared variable.

    Every constant of the model's graph equal to ``y`` — the observations of the
    likelihood and any graph the formulation built from them (e.g. linear mean
    coefficients recovered per draw) — becomes the shared variable, so that
    ``shared.set_value(new_y)`` turns the model (and functions compiled from it) into
    the model of the new data.

    Returns
    -------
    model : pymc.Model
    shared : pytensor SharedVariable

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu", 0.0, 10.0)
    ...     _ = pm.Normal("y", mu, 1.0, observed=np.array([1.0, 2.0]))
    >>> swapped, shared = swappable_observations(model, np.array([1.0, 2.0]))
    >>> logp = swapped.compile_logp()
    >>> shared.set_value(np.array([0.0, 0.0]))
    >>> float(np.round(logp({"mu": 0.0}), 4))  # 2 log N(0; 0, 1) + log N(0; 0, 10)
    -5.0594
    """
    from pymc.model.fgraph import fgraph_from_model, model_from_fgraph

    y = np.asarray(y, dtype=float)
    fgraph, _ = fgraph_from_model(model)
    shared = pytensor.shared(y.copy(), name="y_observed")
    found = [
        v
        for v in fgraph.variables
        if isinstance(v, TensorConstant) and v.data.shape == y.shape and np.array_equal(v.data, y)
    ]
    if not found:
        raise ValueError("the model's graph holds no constant equal to the observed values")
    for constant in found:
        fgraph.replace(constant, shared.astype(constant.dtype), import_missing=True)
    return model_from_fgraph(fgraph, mutate_fgraph=True), shared


@dataclass
class Fitter:
    """One compiled fitted model, its shared observations and the ranked parameters."""

    model: pm.Model
    observed: Any
    space: ValueSpace
    parameters: dict[str, tuple[str, tuple[int, ...]]]
    compile_seconds: float
    #: σ_obs and the formulation's variance partner, sampled as calibrate samples them
    variance_pairs: tuple[tuple[str, ...], ...] = ()


def _ranked_parameters(model: pm.Model, names: list[str]) -> dict[str, tuple[str, tuple]]:
    """Scalar name (``"A"``, ``"delta_mean[1]"``) -> (variable, index) for each element."""
    out: dict[str, tuple[str, tuple]] = {}
    for name in names:
        var = model[name]
        shape = tuple(int(s) for s in var.shape.eval()) if var.ndim else ()
        if not shape:
            out[name] = (name, ())
            continue
        for index in np.ndindex(*shape):  # arviz's names of the elements
            out[f"{name}[{', '.join(map(str, index))}]"] = (name, index)
    return out


def _parameter_names(physics: PhysicsModel, model: pm.Model, created: tuple[str, ...]):
    """Physics parameters, σ_obs when calibrated and the formulation's own parameters.

    Left out: standard-normal auxiliaries (``*_white``), whose meaning differs between the
    simulated and the fitted (coefficients integrated out) forms, and anything over the
    data rows.
    """
    names = [*physics.parameters]
    if "sigma_obs" in model.named_vars:
        names.append("sigma_obs")
    for name in created:
        dims = model.named_vars_to_dims.get(name, ())
        if name.endswith("_white") or "obs" in dims or name in names:
            continue
        names.append(name)
    return names


def build_fitter(physics, data: CalibrationData, formulation: Discrepancy, mode) -> Fitter:
    """Compose the fitted model once, make its observations swappable, compile it."""
    start = time.perf_counter()
    built = compose_model(physics, data, formulation)
    model, observed = swappable_observations(built.model, data.y)
    space = value_space(model, mode=mode)
    names = _parameter_names(physics, model, built.formulation_variables)
    partner = formulation.noise_partner()  # as kohpymc.calibrate passes it to the sampler
    return Fitter(
        model,
        observed,
        space,
        _ranked_parameters(model, names),
        time.perf_counter() - start,
        () if partner is None else (("sigma_obs", *partner),),
    )


def verify_swap(fitter: Fitter, physics, data: CalibrationData, formulation) -> None:
    """The swapped model at other data equals a model composed from those data.

    Guards against a formulation that derived numbers from the observations outside the
    graph (which the swap cannot reach); the test data are the observations permuted,
    so the data-sized default priors are the same.
    """
    permuted = [p for p in (data.y[::-1], np.roll(data.y, 1)) if not np.array_equal(p, data.y)]
    if not permuted:
        return  # constant observations: every permutation is the same data
    other = permuted[0].copy()
    fresh = compose_model(physics, _with_y(data, other), formulation).model
    point = fresh.initial_point(0)
    names = [v.name for v in fresh.free_RVs + fresh.deterministics]
    fitter.observed.set_value(other)
    try:
        got = _logp_and_values(fitter.model, point, names)
        want = _logp_and_values(fresh, point, names)
    finally:
        fitter.observed.set_value(np.asarray(data.y, dtype=float))
    for name, a, b in zip(["logp", *names], got, want, strict=True):
        if not np.allclose(a, b, rtol=1e-8, atol=1e-10, equal_nan=True):
            raise NotImplementedError(
                f"the {formulation.label} formulation uses the observed values outside the "
                f"model graph ({name!r} does not follow new data): it cannot be checked "
                "with one compiled model"
            )


def _logp_and_values(model: pm.Model, point: dict, names: list[str]) -> list[np.ndarray]:
    logp = model.compile_logp(mode="FAST_COMPILE")(point)
    outputs = model.replace_rvs_by_values([model[n] for n in names])
    values = model.compile_fn(
        outputs, inputs=model.value_vars, on_unused_input="ignore", mode="FAST_COMPILE"
    )(point)
    return [np.asarray(logp), *map(np.asarray, values)]


def _with_y(data: CalibrationData, y: np.ndarray, noise_sd: Any = "same") -> CalibrationData:
    """The same inputs with other outputs (and, if given, another known noise sd)."""
    return CalibrationData(
        dict(data.inputs),
        np.asarray(y, dtype=float),
        noise_sd=data.noise_sd if noise_sd == "same" else noise_sd,
        output_name=data.output_name,
        source=data.source,
    )


# -------------------------------------------------------------- the simulation model
@dataclass
class Simulator:
    """A compiled joint draw of the true parameters and ``y`` from one seed."""

    draw: Callable[[], list[np.ndarray]]
    rngs: list[Any]
    names: list[str]
    fixed: dict[str, float]

    def __call__(self, seed: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
        pm.pytensorf.reseed_rngs(self.rngs, seed)
        *values, y = self.draw()
        truth = {n: np.asarray(v, dtype=float) for n, v in zip(self.names, values, strict=True)}
        truth.update({k: np.asarray(v) for k, v in self.fixed.items()})
        return truth, np.asarray(y, dtype=float)


def build_simulator(spec: StudySpec, formulation: Discrepancy, wanted: list[str]) -> Simulator:
    """The data-generating model: the fitted one, or what ``[check.simulate]`` declares."""
    from pytensor.tensor.random.type import RandomGeneratorType

    check: CheckSpec = spec.check
    physics = copy.copy(spec.physics)
    physics.parameters = {**spec.physics.parameters, **check.simulate_parameters}
    data = spec.calibration
    noise_prior = check.simulate_noise_prior
    if check.simulate_noise_sd is not None:
        data = _with_y(data, data.y, noise_sd=check.simulate_noise_sd)
    elif noise_prior is not None:
        data = _with_y(data, data.y, noise_sd=None)
    model = compose_model(
        physics, data, formulation, noise_sd_prior=noise_prior, marginalize=False
    ).model
    fixed = {}
    if "sigma_obs" in wanted and "sigma_obs" not in model.named_vars:
        fixed["sigma_obs"] = float(data.noise_sd)  # type: ignore[arg-type]
    names = [n for n in wanted if n not in fixed]
    missing = [n for n in names if n not in model.named_vars]
    if missing:
        raise ValueError(f"the simulation model has no variable(s) {missing} to draw")
    draw = pm.pytensorf.compile([], [model[n] for n in names] + [model["y"]], mode="FAST_COMPILE")
    rngs = [v for v in draw.get_shared() if isinstance(v.type, RandomGeneratorType)]
    return Simulator(draw, rngs, names, fixed)


@dataclass(frozen=True)
class Recipe:
    """What a worker needs to rebuild the fitted model (plain, picklable)."""

    study: str
    settings: CheckSettings
    setup_hash: str
    model_hash: str


@dataclass(frozen=True)
class Replicate:
    """One task: simulated data and the truth, with the recipe of the fitted model."""

    recipe: Recipe
    index: int
    seed: int
    y: np.ndarray
    truth: dict[str, np.ndarray]


_LOCAL = threading.local()


def _fitter_for(recipe: Recipe) -> Fitter:
    """The compiled fitted model of this thread for ``recipe`` (built on first use)."""
    cache = getattr(_LOCAL, "fitters", None)
    if cache is None:
        cache = _LOCAL.fitters = {}
    if recipe.model_hash not in cache:
        spec = load_study(recipe.study)
        label = recipe.settings.formulation
        cache[recipe.model_hash] = build_fitter(
            spec.physics, spec.calibration, spec.formulations[label], recipe.settings.mode
        )
    return cache[recipe.model_hash]


def cached_fitter(key: str) -> Fitter | None:
    """The compiled fitted model of this thread whose ``model_hash`` is ``key``, if any."""
    return getattr(_LOCAL, "fitters", {}).get(key)


def remember(recipe: Recipe, fitter: Fitter) -> None:
    if getattr(_LOCAL, "fitters", None) is None:
        _LOCAL.fitters = {}
    _LOCAL.fitters[recipe.model_hash] = fitter


def rank_of_truth(draws: np.ndarray, truth: float, n_ranked: int) -> tuple[int, np.ndarray]:
    """Rank of ``truth`` among ``n_ranked`` evenly thinned ``draws``, and those draws.

    ``draws`` has shape ``(chain, draw)``; chains are concatenated and every
    ``(C·D)/L``-th draw kept.  The rank counts the kept draws below the truth, ``0 … L``.

    Examples
    --------
    >>> draws = np.arange(20.0).reshape(2, 10)
    >>> rank_of_truth(draws, 7.5, 5)[0], rank_of_truth(draws, 7.5, 5)[1].tolist()
    (2, [0.0, 4.0, 8.0, 12.0, 16.0])
    """
    flat = np.asarray(draws, dtype=float).reshape(-1)
    kept = flat[(np.arange(n_ranked) * flat.size) // n_ranked]
    return int(np.sum(kept < truth)), kept


def fit_replicate(task: Replicate) -> dict[str, Any]:
    """Calibrate one simulated data set; ranks, coverage and diagnostics as plain values.

    The task function of :func:`kohpymc.sbc.check_calibration`: module-level and taking
    one picklable :class:`Replicate`, so that it can run on a Dask worker, where the
    fitted model is rebuilt from the study file once per worker thread.

    Returns
    -------
    dict
        ``index``, ``seed``, ``y``, per parameter ``truth``, ``rank``, ``cover50``,
        ``cover90``, ``quantiles`` (5, 25, 50, 75, 95 %), ``thinned`` draws, ``r_hat``,
        ``r_hat_limit`` (:func:`kohpymc.diagnostics.rhat_limit`), ``ess_bulk``,
        ``ess_tail``; ``divergences``, ``problems`` (empty when the fit is
        usable), ``sampler``, ``reparameterization`` and ``seconds``.

    Examples
    --------
    >>> result = fit_replicate(tasks["0"])  # doctest: +SKIP
    >>> result["rank"]  # doctest: +SKIP
    {'A': 41, 'k': 77, 'sigma_obs': 12}
    """
    start = time.perf_counter()
    fitter = _fitter_for(task.recipe)
    settings = task.recipe.settings
    fitter.observed.set_value(np.asarray(task.y, dtype=float))
    fit_seed = int(np.random.SeedSequence(task.seed, spawn_key=(1,)).generate_state(1)[0])
    idata, report = sample_posterior(
        fitter.model,
        space=fitter.space,
        sampler=settings.sampler,
        draws=settings.draws,
        tune=settings.tune,
        chains=settings.chains,
        target_accept=settings.target_accept,
        random_seed=fit_seed,
        reparameterize=settings.reparameterize,
        mode=settings.mode,
        variance_pairs=fitter.variance_pairs,
    )
    result = _score(idata, fitter, task, settings)
    result["problems"] = _problems(idata, result, settings, report)
    result.update(
        sampler=report.sampler,
        reparameterization=report.reparameterization.get("kind", "none"),
        seconds=time.perf_counter() - start,
    )
    return result


def _score(idata, fitter: Fitter, task: Replicate, settings: CheckSettings) -> dict[str, Any]:
    """Truth, rank, interval coverage, quantiles and thinned draws of every parameter."""
    out: dict[str, Any] = {"index": task.index, "seed": task.seed, "y": np.asarray(task.y)}
    for key in ("truth", "rank", "cover50", "cover90", "quantiles", "thinned", "r_hat_limit"):
        out[key] = {}
    posterior = idata.posterior
    for name, (var, index) in fitter.parameters.items():
        draws = posterior[var].transpose("chain", "draw", ...).values[(..., *index)]
        truth = float(np.asarray(task.truth[var])[index])
        rank, kept = rank_of_truth(draws, truth, settings.rank_draws)
        q = np.quantile(draws, [0.05, 0.25, 0.5, 0.75, 0.95])
        out["truth"][name] = truth
        out["rank"][name] = rank
        out["cover50"][name] = bool(q[1] <= truth <= q[3])
        out["cover90"][name] = bool(q[0] <= truth <= q[4])
        out["quantiles"][name] = q
        out["thinned"][name] = kept
        out["r_hat_limit"][name] = rhat_limit(draws, parameters=len(fitter.parameters))
    table = sampler_diagnostics(idata, sorted({v for v, _ in fitter.parameters.values()}))
    for key in ("r_hat", "ess_bulk", "ess_tail"):
        out[key] = {name: float(table.loc[name, key]) for name in fitter.parameters}
    out["divergences"] = n_divergences(idata) or 0
    return out


def _problems(idata, result: dict, settings: CheckSettings, report) -> list[str]:
    """Why this replicate's posterior cannot be trusted (empty when it can)."""
    problems = []
    limits = result["r_hat_limit"]
    over = {k: v for k, v in result["r_hat"].items() if not v <= limits[k]}
    if over:
        name = max(over, key=lambda k: over[k] - limits[k])
        problems.append(f"r_hat {over[name]:.4f} > {limits[name]:.4f} ({name}; the limit "
                        "well-mixed chains of this length reach by chance)")  # fmt: skip
    ess = min(min(result["ess_bulk"].values()), min(result["ess_tail"].values()))
    if not ess >= settings.min_ess:
        problems.append(f"ESS {ess:.0f} < {settings.min_ess}")
    if result["divergences"]:
        problems.append(f"{result['divergences']} divergent transition(s)")
    if report.failed_evaluations:
        problems.append(f"{report.failed_evaluations} failed log-density evaluation(s)")
    return problems
