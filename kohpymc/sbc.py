r"""Simulation-based calibration: whether a calibration set-up recovers the truth.

For one formulation of a study, :func:`check_calibration` repeats ``N`` times (Talts,
Betancourt, Simpson, Vehtari & Gelman 2018, "Validating Bayesian inference algorithms
with simulation-based calibration", arXiv:1804.06788):

1. draw the parameters (θ, the discrepancy parameters, σ_obs) *and* data ``ỹ`` at the
   study's calibration inputs jointly from the prior predictive of the composed PyMC
   model (:func:`kohpymc.model.compose_model`, with the linear mean coefficients not
   integrated out, so every parameter has a drawn value);
2. calibrate on ``ỹ`` with the study's sampler (:func:`kohpymc.sampling.sample_posterior`);
3. record, for every scalar parameter, the rank of its true value among ``L`` posterior
   draws thinned to be nearly independent, and whether the central 50 % and 90 %
   posterior intervals contain it.

If the sampler draws from the exact posterior of a model that generated the data, every
rank is uniform on ``0 … L`` and an ``α`` interval covers the truth in a fraction ``α``
of the replicates.  The coverage table gives each fraction with its binomial standard
error ``√(p(1−p)/N)``; the verdict fails a parameter whose 90 % or 50 % coverage is more
than three null standard errors (``√(α(1−α)/N)``) from ``α`` or whose rank histogram a
chi-square test rejects at ``p < 0.001``.  Replicates whose fit shows sampler trouble
(r̂ > 1.01, bulk or tail ESS below ``max(100, L + 1)``, divergences) are listed and left
out of the table; more than 10 % of them fails the check, since leaving them out then
biases it.

**One compile serves every replicate.**  The fitted model is composed once from the
study's data; every constant in its graph equal to the observed values (the likelihood's
observations and what a formulation built from them) is replaced by one shared variable
(:func:`swappable_observations`), and the log density is compiled once
(:func:`kohpymc.value_space.value_space`).  A replicate sets the shared variable to its
simulated data and samples.  The default priors that the model sizes from the data
(``HalfNormal(sd(y))`` for σ_obs, ...) are those of the study's data in the simulation
and in every fit alike.

A deliberately wrong set-up, for which the check must fail, is declared in the study's
``[check.simulate]`` table (:class:`kohpymc.config.CheckSpec`): other priors for the
true physics parameters, or a fixed simulation noise sd (e.g. five times the fit's
``[data] noise_sd``).

Replicates run through ``run_tasks`` (in-process by default, on a Dask cluster with
``workers > 1`` or a scheduler address); each result is written to
``DIR/replicates/`` the moment it finishes and reused by a rerun when the set-up hash and
the replicate's seed match (:mod:`kohpymc.sbc_files`).
"""

from __future__ import annotations

import copy
import hashlib
import inspect
import json
import statistics
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pymc as pm
import pytensor
import xarray as xr
from pytensor.tensor.variable import TensorConstant
from scipy import stats

from kohpymc.checks import check_count
from kohpymc.config import CheckSpec, StudySpec, load_study
from kohpymc.data import CalibrationData
from kohpymc.diagnostics import RHAT_MAX, n_divergences, sampler_diagnostics
from kohpymc.discrepancy.base import Discrepancy
from kohpymc.model import compose_model
from kohpymc.physics import PhysicsModel
from kohpymc.sampling import sample_posterior
from kohpymc.value_space import ValueSpace, value_space

__all__ = [
    "CalibrationCheck",
    "CheckSettings",
    "check_calibration",
    "rank_of_truth",
    "rank_uniformity",
    "swappable_observations",
]

#: the two central intervals whose coverage is checked
LEVELS = (0.5, 0.9)
#: null standard errors a coverage may be off before the verdict fails
COVERAGE_Z = 3.0
#: chi-square p-value below which ranks are not uniform
UNIFORMITY_ALPHA = 1e-3
#: fraction of replicates with sampler trouble above which the check fails
MAX_FLAGGED = 0.10
#: the least effective sample size of a usable replicate
MIN_ESS = 100


# --------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class CheckSettings:
    """The resolved settings of one check (command line over ``[check]`` over ``[sampling]``).

    Examples
    --------
    >>> CheckSettings("M0", replicates=10, draws=300, tune=300, chains=2, seed=1).rank_draws
    99
    """

    formulation: str
    replicates: int
    draws: int
    tune: int
    chains: int
    seed: int
    rank_draws: int = 99
    sampler: str | None = None
    target_accept: float = 0.9
    reparameterize: bool = True
    mode: str | None = None

    @property
    def min_ess(self) -> int:
        """Bulk and tail ESS a replicate needs: its ``L`` thinned draws nearly independent."""
        return max(MIN_ESS, self.rank_draws + 1)


def _resolve(spec: StudySpec, overrides: Mapping[str, Any]) -> CheckSettings:
    """Command-line values, else ``[check]``, else ``[sampling]``, else the defaults."""
    check, sampling = spec.check, spec.sampling

    def pick(key: str, default: Any, sampling_key: str | None = None) -> Any:
        for value in (overrides.get(key), getattr(check, key), sampling.get(sampling_key or key)):
            if value is not None:
                return value
        return default

    label = pick("formulation", "M0")
    if label not in spec.formulations:
        raise ValueError(
            f"{spec.source}: formulation {label!r} is not one of the study's formulations "
            f"{list(spec.formulations)}"
        )
    replicates = pick("replicates", None)
    if replicates is None:
        raise ValueError(f"{spec.source}: give the number of replicates ([check] replicates)")
    settings = CheckSettings(
        formulation=label,
        replicates=replicates,
        draws=pick("draws", 1000),
        tune=pick("tune", 1000),
        chains=pick("chains", 4),
        seed=pick("seed", 0, "random_seed"),
        rank_draws=pick("rank_draws", 99),
        sampler=sampling.get("sampler", "smc" if sampling.get("method") == "smc" else None),
        target_accept=sampling.get("target_accept")
        or spec.formulations[label].default_target_accept,
        reparameterize=sampling.get("reparameterize", True),
        mode=sampling.get("mode"),
    )
    _check_settings(settings)
    return settings


def _check_settings(settings: CheckSettings) -> None:
    for key in ("replicates", "draws", "tune", "chains", "rank_draws"):
        check_count(getattr(settings, key), key)
    check_count(settings.seed, "seed", minimum=0)
    if settings.rank_draws > settings.draws * settings.chains:
        raise ValueError(
            f"rank_draws = {settings.rank_draws} thinned draws need at least that many "
            f"posterior draws; draws × chains = {settings.draws * settings.chains}"
        )


def replicate_seed(seed: int, index: int) -> int:
    """The seed of replicate ``index``: from the check's seed and the index only.

    Examples
    --------
    >>> replicate_seed(1, 0) == replicate_seed(1, 0) != replicate_seed(1, 1)
    True
    """
    return int(np.random.SeedSequence(seed, spawn_key=(index,)).generate_state(1)[0])


# ------------------------------------------------------------------- the fitted model
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
class _Fitter:
    """One compiled fitted model, its shared observations and the ranked parameters."""

    model: pm.Model
    observed: Any
    space: ValueSpace
    parameters: dict[str, tuple[str, tuple[int, ...]]]
    compile_seconds: float


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


def _build_fitter(physics, data: CalibrationData, formulation: Discrepancy, mode) -> _Fitter:
    start = time.perf_counter()
    built = compose_model(physics, data, formulation)
    model, observed = swappable_observations(built.model, data.y)
    space = value_space(model, mode=mode)
    names = _parameter_names(physics, model, built.formulation_variables)
    return _Fitter(
        model, observed, space, _ranked_parameters(model, names), time.perf_counter() - start
    )


def _verify_swap(fitter: _Fitter, physics, data: CalibrationData, formulation) -> None:
    """The swapped model at other data equals a model composed from those data.

    Guards against a formulation that derived numbers from the observations outside the
    graph (which the swap cannot reach); the test data are the observations reversed,
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
class _Simulator:
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


def _build_simulator(spec: StudySpec, formulation: Discrepancy, wanted: list[str]) -> _Simulator:
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
    return _Simulator(draw, rngs, names, fixed)


# ------------------------------------------------------------------------ set-up hash
def _source(function: Any) -> str:
    if function is None:
        return ""
    try:
        return inspect.getsource(function)
    except (OSError, TypeError):
        return f"{getattr(function, '__module__', '')}.{getattr(function, '__qualname__', '')}"


def _digest(content: Any) -> str:
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=repr).encode()).hexdigest()


def model_hash(spec: StudySpec, label: str, mode: str | None = None) -> str:
    """A hash of what the compiled fitted model depends on.

    The physics function's (and Jacobian's) source, the priors, the calibration data,
    the formulation and the compile mode.
    """
    physics, data = spec.physics, spec.calibration
    formulation = spec.formulations[label]
    try:
        described: Any = formulation.to_dict()
    except TypeError:
        described = repr(formulation)
    return _digest(
        {
            "physics": [physics.name, physics.backend, _source(physics.function)],
            "jacobian": _source(physics.jacobian),
            "priors": {k: repr(v) for k, v in physics.parameters.items()},
            "inputs": {k: hashlib.sha256(v.tobytes()).hexdigest() for k, v in data.inputs.items()},
            "y": hashlib.sha256(np.asarray(data.y, float).tobytes()).hexdigest(),
            "noise_sd": data.noise_sd,
            "formulation": described,
            "mode": mode,
        }
    )


def setup_hash(spec: StudySpec, settings: CheckSettings) -> str:
    """A hash of everything a replicate's result depends on except its seed.

    :func:`model_hash`, ``[check.simulate]``, the sampler settings and the kohpymc
    version; not the number of replicates or the base seed.

    Examples
    --------
    >>> from kohpymc.config import load_study
    >>> from kohpymc.examples import decay
    >>> spec = load_study(decay.STUDY_FILE)
    >>> a = setup_hash(spec, CheckSettings("M0", 10, 300, 300, 2, 1))
    >>> a == setup_hash(spec, CheckSettings("M0", 50, 300, 300, 2, 7))
    True
    >>> a == setup_hash(spec, CheckSettings("M0", 10, 400, 300, 2, 1))
    False
    """
    from kohpymc import __version__

    check = spec.check
    return _digest(
        {
            "kohpymc": __version__,
            "model": model_hash(spec, settings.formulation, settings.mode),
            "simulate": [
                {k: repr(v) for k, v in check.simulate_parameters.items()},
                check.simulate_noise_sd,
                repr(check.simulate_noise_prior),
            ],
            "settings": {
                k: v for k, v in asdict(settings).items() if k not in ("replicates", "seed")
            },
        }
    )


# ------------------------------------------------------------------------ replicates
@dataclass(frozen=True)
class _Recipe:
    """What a worker needs to rebuild the fitted model (plain, picklable)."""

    study: str
    settings: CheckSettings
    setup_hash: str
    model_hash: str


@dataclass(frozen=True)
class _Replicate:
    """One task: simulated data and the truth, with the recipe of the fitted model."""

    recipe: _Recipe
    index: int
    seed: int
    y: np.ndarray
    truth: dict[str, np.ndarray]


_LOCAL = threading.local()


def _fitter_for(recipe: _Recipe) -> _Fitter:
    """The compiled fitted model of this thread for ``recipe`` (built on first use)."""
    cache = getattr(_LOCAL, "fitters", None)
    if cache is None:
        cache = _LOCAL.fitters = {}
    if recipe.model_hash not in cache:
        spec = load_study(recipe.study)
        label = recipe.settings.formulation
        cache[recipe.model_hash] = _build_fitter(
            spec.physics, spec.calibration, spec.formulations[label], recipe.settings.mode
        )
    return cache[recipe.model_hash]


def _remember(recipe: _Recipe, fitter: _Fitter) -> None:
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


def _fit_replicate(task: _Replicate) -> dict[str, Any]:
    """Calibrate one simulated data set; ranks, coverage and diagnostics as plain values."""
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
    )
    result = _score(idata, fitter, task, settings)
    result["problems"] = _problems(idata, result, settings, report)
    result.update(
        sampler=report.sampler,
        reparameterization=report.reparameterization.get("kind", "none"),
        seconds=time.perf_counter() - start,
    )
    return result


def _score(idata, fitter: _Fitter, task: _Replicate, settings: CheckSettings) -> dict[str, Any]:
    """Truth, rank, interval coverage, quantiles and thinned draws of every parameter."""
    out: dict[str, Any] = {"index": task.index, "seed": task.seed, "y": np.asarray(task.y)}
    for key in ("truth", "rank", "cover50", "cover90", "quantiles", "thinned"):
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
    table = sampler_diagnostics(idata, sorted({v for v, _ in fitter.parameters.values()}))
    for key in ("r_hat", "ess_bulk", "ess_tail"):
        out[key] = {name: float(table.loc[name, key]) for name in fitter.parameters}
    out["divergences"] = n_divergences(idata) or 0
    return out


def _problems(idata, result: dict, settings: CheckSettings, report) -> list[str]:
    """Why this replicate's posterior cannot be trusted (empty when it can)."""
    problems = []
    r_hat = max(result["r_hat"].values())
    if not r_hat <= RHAT_MAX:
        problems.append(f"r_hat {r_hat:.4f} > {RHAT_MAX}")
    ess = min(min(result["ess_bulk"].values()), min(result["ess_tail"].values()))
    if not ess >= settings.min_ess:
        problems.append(f"ESS {ess:.0f} < {settings.min_ess}")
    if result["divergences"]:
        problems.append(f"{result['divergences']} divergent transition(s)")
    if report.failed_evaluations:
        problems.append(f"{report.failed_evaluations} failed log-density evaluation(s)")
    return problems


# ----------------------------------------------------------------- running the tasks
@dataclass
class _Outcome:
    """One finished task (the shape ``kohpymc.execution.run_tasks`` yields)."""

    key: str
    value: Any
    error: BaseException | None
    seconds: float


def _run_tasks_in_process(
    function: Callable[[Any], Any],
    items: Mapping[str, Any],
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: Any = None,
) -> Iterator[_Outcome]:
    """STAND-IN for ``kohpymc.execution.run_tasks`` (branch wt-dask): in-process only.

    Same signature and outcomes; replace by ``kohpymc.execution.run_tasks`` when merging.
    """
    if workers > 1 or scheduler:
        raise RuntimeError(
            "--workers/--scheduler need kohpymc.execution (Dask), not in this build; "
            "run without them"
        )
    for key, item in items.items():
        start = time.perf_counter()
        try:
            value, error = function(item), None
        except Exception as err:  # noqa: BLE001 - reported per task
            value, error = None, err
        yield _Outcome(key, value, error, time.perf_counter() - start)


def _run_tasks() -> Callable[..., Any]:
    try:  # the Dask executor, once merged
        from kohpymc.execution import run_tasks  # type: ignore[import-not-found]
    except ImportError:
        return _run_tasks_in_process
    return run_tasks  # pragma: no cover - not on this branch


def _unpack(outcome: Any) -> tuple[str, Any, Any, float]:
    if hasattr(outcome, "key"):
        return outcome.key, outcome.value, outcome.error, float(outcome.seconds)
    key, value, error, seconds = outcome
    return key, value, error, float(seconds)


# ---------------------------------------------------------------------- the summary
def rank_uniformity(ranks: np.ndarray, n_ranked: int) -> tuple[float, int, np.ndarray]:
    """Chi-square test that ranks ``0 … L`` are uniform: p-value, bins and bin counts.

    The ``L + 1`` rank values are pooled into ``B`` equal bins (``B`` divides ``L + 1``,
    at most 20, at least 5 expected counts per bin when possible).

    Examples
    --------
    >>> p, bins, counts = rank_uniformity(np.arange(100), 99)
    >>> round(p, 3), bins, counts.tolist()[:3]
    (1.0, 20, [5, 5, 5])
    """
    ranks = np.asarray(ranks, dtype=int)
    values = n_ranked + 1
    divisors = [b for b in range(min(20, values), 0, -1) if values % b == 0]
    enough = [b for b in divisors if ranks.size / b >= 5]
    bins = enough[0] if enough else divisors[-1]
    counts = np.bincount(ranks * bins // values, minlength=bins)
    if bins < 2:
        return float("nan"), bins, counts
    return float(stats.chisquare(counts).pvalue), bins, counts


def coverage_table(records: list[dict], parameters: list[str], n_ranked: int) -> pd.DataFrame:
    """Per parameter: coverage of the 50 % and 90 % intervals with binomial SEs, ranks.

    Examples
    --------
    >>> rec = [{"cover50": {"a": i % 2 == 0}, "cover90": {"a": True}, "rank": {"a": i}}
    ...        for i in range(10)]
    >>> coverage_table(rec, ["a"], 9).loc["a", ["cover50", "cover90", "mean_rank"]].tolist()
    [0.5, 1.0, 0.5]
    """
    rows = {}
    n = len(records)
    for name in parameters:
        row: dict[str, Any] = {"replicates": n}
        for level in LEVELS:
            key = f"cover{round(100 * level)}"
            p = float(np.mean([r[key][name] for r in records])) if n else float("nan")
            row[key] = p
            row[f"{key}_se"] = float(np.sqrt(p * (1 - p) / n)) if n else float("nan")
        ranks = np.array([r["rank"][name] for r in records], dtype=int)
        row["mean_rank"] = float(ranks.mean() / n_ranked) if n else float("nan")
        row["chi2_p"], row["rank_bins"], _ = rank_uniformity(ranks, n_ranked)
        rows[name] = row
    frame = pd.DataFrame.from_dict(rows, orient="index")
    frame.index.name = "parameter"
    return frame


def verdict(table: pd.DataFrame, n_finished: int, n_flagged: int, label: str) -> tuple[bool, str]:
    """PASS or FAIL with the reasons, from the coverage table (see the module docstring).

    Examples
    --------
    >>> t = pd.DataFrame({"replicates": [200], "cover50": [0.5], "cover50_se": [0.035],
    ...                   "cover90": [0.41], "cover90_se": [0.0348], "chi2_p": [0.3]},
    ...                  index=["sigma_obs"])
    >>> print(verdict(t, 200, 0, "M0")[1])  # doctest: +NORMALIZE_WHITESPACE
    FAIL: sigma_obs 90 % coverage 0.41 ± 0.03 (expected 0.90): the set-up does not recover
    the truth
    """
    trouble = ""
    if n_finished and n_flagged / n_finished > MAX_FLAGGED:
        trouble = (
            f"{n_flagged} of {n_finished} replicates had sampler trouble (more than "
            f"{MAX_FLAGGED:.0%}; leaving them out biases the check): longer chains "
            "(--draws/--tune) or a better-posed set-up needed"
        )
    reasons = []
    for name, row in table.iterrows():
        n = int(row["replicates"])
        if n == 0:
            continue
        for level in (0.9, 0.5):
            key = f"cover{round(100 * level)}"
            if abs(row[key] - level) > COVERAGE_Z * np.sqrt(level * (1 - level) / n):
                reasons.append(
                    f"{name} {round(100 * level)} % coverage {row[key]:.2f} ± "
                    f"{row[key + '_se']:.2f} (expected {level:.2f})"
                )
        if row["chi2_p"] < UNIFORMITY_ALPHA:
            reasons.append(f"{name} ranks not uniform (chi-square p = {row['chi2_p']:.2g})")
    if reasons:
        text = "; ".join(reasons) + ": the set-up does not recover the truth"
        return False, "FAIL: " + text + (f"; also {trouble}" if trouble else "")
    if trouble:
        return False, "FAIL: " + trouble
    covers = ", ".join(
        f"{row['cover90']:.2f} ± {row['cover90_se']:.2f} ({name})" for name, row in table.iterrows()
    )
    n_used = int(table["replicates"].iloc[0]) if len(table) else 0
    return True, (
        f"PASS: {label}, {n_used} replicates: every parameter's 90 % interval covers the truth "
        f"({covers}); 50 % coverage and rank histograms consistent with uniform ranks"
    )


# ------------------------------------------------------------------------- the check
@dataclass
class CalibrationCheck:
    """The result of :func:`check_calibration`.

    Attributes
    ----------
    settings : CheckSettings
    passed : bool
    verdict : str
        One line, ``"PASS: ..."`` or ``"FAIL: ..."``.
    table : pandas.DataFrame
        Per parameter: ``cover50``, ``cover90`` (with ``_se``), ``mean_rank`` (``/L``),
        ``chi2_p``, over the usable replicates.
    ranks : xarray.Dataset
        ``rank``, ``truth``, ``cover50``, ``cover90``, ``r_hat``, ``ess_bulk``,
        ``ess_tail`` over ``(replicate, parameter)``, ``thinned`` over ``(replicate,
        parameter, draw)``, ``seed`` and ``usable`` over ``replicate``.
    records : list of dict
        Every finished replicate's result.
    failures : dict index -> str
        Replicates whose fit raised.
    timings : dict
        Seconds: ``setup_compile`` (building and compiling the fitted model, when this run
        fitted replicates), ``replicate_mean``/``_median``/``s_total`` (each replicate's fit,
        reused ones as measured when they were fitted) and ``wall`` (this run).
    reused : int
        Replicates read back from an earlier run.
    files : list of Path
    """

    settings: CheckSettings
    passed: bool
    verdict: str
    table: pd.DataFrame
    ranks: xr.Dataset
    records: list[dict[str, Any]]
    failures: dict[int, str] = field(default_factory=dict)
    timings: dict[str, Any] = field(default_factory=dict)
    reused: int = 0
    files: list[Path] = field(default_factory=list)
    setup_hash: str = ""

    @property
    def flagged(self) -> list[dict[str, Any]]:
        """The finished replicates with sampler trouble (left out of the table)."""
        return [r for r in self.records if r["problems"]]


def check_calibration(
    study: str | Path | StudySpec,
    *,
    replicates: int | None = None,
    formulation: str | None = None,
    draws: int | None = None,
    tune: int | None = None,
    chains: int | None = None,
    seed: int | None = None,
    rank_draws: int | None = None,
    out_dir: str | Path | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    fresh: bool = False,
    progress: Callable[[str], None] | None = None,
) -> CalibrationCheck:
    """Simulation-based calibration of one formulation of a study (see the module docstring).

    Parameters
    ----------
    study : path or StudySpec
        The study file (or its :func:`~kohpymc.config.load_study` result).
    replicates : int, optional
        Number of simulated data sets (else ``[check] replicates``).
    formulation : str, optional
        Label of the formulation (else ``[check] formulation``, else ``"M0"``).
    draws, tune, chains, seed, rank_draws : int, optional
        Override ``[check]`` (which overrides ``[sampling]``); ``rank_draws`` is ``L``,
        the number of thinned posterior draws a rank is computed among (default 99).
    out_dir : path, optional
        Write the replicate files, ``table.md``/``.csv``, ``ranks.nc``, ``ranks.png``
        and ``check.json`` here; a rerun into the same folder reuses every replicate whose
        set-up hash and seed match.
    workers, scheduler :
        Run replicates on a Dask cluster of ``workers`` processes or at ``scheduler``.
    fresh : bool
        Recompute every replicate.
    progress : callable, optional
        Receives one line per finished replicate.

    Returns
    -------
    CalibrationCheck

    Examples
    --------
    >>> from kohpymc.examples import decay
    >>> check = check_calibration(decay.STUDY_FILE, replicates=4, draws=200, tune=200,
    ...                           chains=2, seed=1)  # doctest: +SKIP
    >>> check.table.loc["k", "cover90"] <= 1.0  # doctest: +SKIP
    True
    """
    from kohpymc import sbc_files

    started = time.perf_counter()
    spec = study if isinstance(study, StudySpec) else load_study(study)
    overrides = dict(
        replicates=replicates, formulation=formulation, draws=draws, tune=tune,
        chains=chains, seed=seed, rank_draws=rank_draws,
    )  # fmt: skip
    settings = _resolve(spec, overrides)
    recipe = _Recipe(
        str(Path(spec.source).resolve()),
        settings,
        setup_hash(spec, settings),
        model_hash(spec, settings.formulation, settings.mode),
    )
    out = None if out_dir is None else Path(out_dir)
    seeds = [replicate_seed(settings.seed, i) for i in range(settings.replicates)]
    done = {} if out is None or fresh else sbc_files.read_replicates(out, recipe.setup_hash, seeds)
    say = progress or (lambda _msg: None)
    if done:
        say(f"{len(done)} of {settings.replicates} replicates reused from {out}")
    timings: dict[str, Any] = {}
    todo = [i for i in range(settings.replicates) if i not in done]
    records, failures = dict(done), {}
    if todo:
        fitter = _prepare(spec, settings, recipe, timings)
        tasks = _tasks(spec, settings, recipe, fitter, todo, seeds)
        for index, result, error in _collect(tasks, workers, scheduler, say, settings):
            if error is not None:
                failures[index] = error
                continue
            records[index] = result
            if out is not None:
                sbc_files.write_replicate(out, recipe.setup_hash, result)
    return _finish(spec, settings, recipe, records, failures, done, timings, started, out)


def _prepare(spec: StudySpec, settings: CheckSettings, recipe: _Recipe, timings) -> _Fitter:
    """Compile the fitted model once (checking that data can be swapped into it)."""
    cached = getattr(_LOCAL, "fitters", {}).get(recipe.model_hash)
    if cached is not None:  # an earlier check of the same model in this thread
        timings["setup_compile"] = 0.0
        return cached
    formulation = spec.formulations[settings.formulation]
    fitter = _build_fitter(spec.physics, spec.calibration, formulation, settings.mode)
    _verify_swap(fitter, spec.physics, spec.calibration, formulation)
    _remember(recipe, fitter)
    timings["setup_compile"] = fitter.compile_seconds
    return fitter


def _tasks(spec, settings, recipe, fitter: _Fitter, todo: list[int], seeds) -> dict[str, Any]:
    """Simulate every replicate still to do (cheap; one compiled draw function)."""
    formulation = spec.formulations[settings.formulation]
    wanted = sorted({var for var, _ in fitter.parameters.values()})
    simulate = _build_simulator(spec, formulation, wanted)
    tasks = {}
    for index in todo:
        sim_seed = int(np.random.SeedSequence(seeds[index], spawn_key=(0,)).generate_state(1)[0])
        truth, y = simulate(sim_seed)
        tasks[str(index)] = _Replicate(recipe, index, seeds[index], y, truth)
    return tasks


def _collect(tasks, workers, scheduler, say, settings: CheckSettings):
    """Run the tasks; yield ``(index, result, error message)`` as each finishes."""
    run = _run_tasks()
    finished = flagged = 0
    for outcome in run(_fit_replicate, tasks, workers=workers, scheduler=scheduler):
        key, value, error, seconds = _unpack(outcome)
        finished += 1
        if error is not None:
            message = (
                f"{type(error).__name__}: {error}" if isinstance(error, BaseException) else error
            )
            say(f"replicate {key}: failed ({str(message).splitlines()[0]})")
            yield int(key), None, str(message)
            continue
        flagged += bool(value["problems"])
        say(
            f"replicate {key} done in {seconds:.1f} s ({finished}/{len(tasks)}; "
            f"{flagged} with sampler trouble)"
            + (f": {'; '.join(value['problems'])}" if value["problems"] else "")
        )
        yield int(key), value, None


def _finish(spec, settings, recipe, records, failures, done, timings, started, out):
    """Table, verdict, ranks dataset and (with ``out``) the files."""
    from kohpymc import sbc_files

    ordered = [records[i] for i in sorted(records)]
    if not ordered:
        raise RuntimeError(
            f"no replicate of {settings.formulation} finished: "
            + "; ".join(f"{i}: {m}" for i, m in sorted(failures.items())[:3])
        )
    usable = [r for r in ordered if not r["problems"]]
    names = list(ordered[0]["rank"])
    table = coverage_table(usable, names, settings.rank_draws)
    passed, line = verdict(table, len(ordered), len(ordered) - len(usable), settings.formulation)
    seconds = [float(r["seconds"]) for r in ordered]  # reused ones: when they were fitted
    timings["replicate_mean"] = statistics.fmean(seconds)
    timings["replicate_median"] = statistics.median(seconds)
    timings["replicates_total"] = sum(seconds)
    timings["wall"] = time.perf_counter() - started
    result = CalibrationCheck(
        settings, passed, line, table, sbc_files.ranks_dataset(ordered, names, settings),
        ordered, failures, timings, len(done), [], recipe.setup_hash,
    )  # fmt: skip
    if out is not None:
        sbc_files.write_check(out, result, spec.source)
    return result
