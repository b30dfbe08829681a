r"""Running the sampler: nutpie by default, PyMC's NUTS or SMC on request, checked afterwards.

:func:`sample_posterior` is the one place :func:`kohpymc.calibrate` samples:

* ``sampler="nutpie"`` (the default): the model's log density and gradient are compiled
  once by PyTensor (:mod:`kohpymc.value_space`), the posterior mode and a whitening map
  are found (:mod:`kohpymc.reparameterization`), and nutpie's Rust NUTS samples the
  whitened coordinates, with chains started around the mode.  Draws are mapped back,
  so the InferenceData holds the user's parameters.  When the model's log density is
  pure PyTensor, the density in the sampling coordinates is compiled by numba as a whole
  (:mod:`kohpymc.native`: no Python per evaluation, chains on ``cores`` threads);
  otherwise (e.g. a numpy physics function) nutpie calls it through Python on one
  thread.  When nutpie cannot be used (not installed, or the set-up fails) PyMC's NUTS
  runs instead and the reason is recorded.
* ``sampler="pymc"``: :func:`pymc.sample` (PyMC's NUTS), started at the mode when one
  was found.
* ``sampler="smc"``: :func:`pymc.sample_smc`, which needs no gradient.

BLAS threads are limited to one while sampling, and :func:`kohpymc.calibrate` and
:func:`kohpymc.predict` hold that limit for their whole call (``threadpoolctl``,
so a script or notebook gets it without ``OPENBLAS_NUM_THREADS``): the matrices here
are small, chains already run in parallel, and on a 2-core machine OpenBLAS's spinning
threads made a GP calibration 4× slower.  The result's :class:`SamplingReport` says
which sampler and which reparameterisation ran, and why.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import threading
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import arviz as az
import numpy as np
import pymc as pm

from kohpymc.chain_processes import GroupResult, sample_chains
from kohpymc.checks import SAMPLERS, check_sampler
from kohpymc.diagnostics import n_divergences
from kohpymc.funnel import funnel_plan
from kohpymc.prior_bounds import hits_in_draws, warn_hits
from kohpymc.progress import report_note, report_phase
from kohpymc.reparameterization import Coordinates, Reparameterization, VarianceShare, plan
from kohpymc.scale_funnel import scale_funnel_plan
from kohpymc.second_run import mixing, plan_second_run
from kohpymc.value_space import (
    ValueSpace,
    nudged,
    quiet_density_errors,
    transformed_value,
    value_space,
)

__all__ = [
    "CURVED_TARGET_ACCEPT",
    "SAMPLERS",
    "SamplingReport",
    "choose_sampler",
    "sample_posterior",
    "target_accept_for",
    "variance_shares",
]

#: NUTS target acceptance on a curved plan (``Reparameterization.curved``) when the caller
#: sets none.  Such a map is fitted to the ridge at a few points; beyond them the curvature
#: in ``z`` grows (dielectric M0: the largest Hessian eigenvalue is 1 at the mode, 3.6 at
#: the median draw and 10-28 at the 5 % of draws far along E_A's axis), and leapfrog steps
#: of h are unstable where it exceeds (2/h)².  At 0.9, M0's step was 0.51-0.53 and 3 of
#: 4000 draws diverged; at 0.95, 0.40-0.42 and none, for 1.37× the leapfrog steps.
CURVED_TARGET_ACCEPT = 0.95


@dataclass
class SamplingReport:
    """What ran: the sampler, why, and the reparameterisation.

    Attributes
    ----------
    sampler : str
        ``"nutpie"``, ``"pymc"`` or ``"smc"`` — the one that produced the draws.
    requested : str
        The one asked for.
    reason : str
        Why ``sampler`` differs from ``requested`` (empty when it does not).
    reparameterization : dict
        :meth:`Reparameterization.to_dict` (``{"kind": "none", ...}`` when not used).
    timings : dict
        Seconds spent compiling, finding the mode and sampling.
    failed_evaluations : int
        Log-density evaluations that raised during sampling (counted as zero density).
    compile_mode : str
        ``"NUMBA"`` or ``"C"``: the PyTensor backend of the log density, and why when
        NUMBA was wanted but failed (``"C (NUMBA failed: ...)"``).
    chain_threads : int
        Threads nutpie's chains ran on: ``cores`` on the native path, one through the
        Python callback (every chain calls the log density through one lock).
    chain_processes : str
        Processes nutpie's chains ran in when the log density is a Python callback
        (:mod:`kohpymc.chain_processes`): one per core on Linux, else ``"1 (reason)"``;
        ``"1"`` on the native path.
    nutpie_backend : str
        How nutpie evaluated the log density: ``"numba-native"`` (the whole density in
        the sampling coordinates compiled by numba, :mod:`kohpymc.native`) or
        ``"python"`` (a Python callback), with the reason the native path was not
        taken (``"python (...)"``); empty when nutpie did not run.
    prior_bounds : list of dict
        Parameters whose draws lie against a prior bound
        (:func:`kohpymc.prior_bounds.hits_in_draws`), each also warned about (NUTS
        samplers; not checked after SMC).
    target_accept : float or None
        NUTS target acceptance of the draws kept (:func:`target_accept_for`, or the
        second run's; None for SMC).
    second_run : dict
        Empty unless the chains were sampled again (:mod:`kohpymc.second_run`): why,
        ``target_accept``, ``draws``, ``divergences`` and ``smallest_ess_bulk`` of both
        runs and the first run's sampling seconds; the draws are the second run's.
    """

    sampler: str
    requested: str
    reason: str = ""
    reparameterization: dict[str, Any] = field(default_factory=lambda: {"kind": "none"})
    timings: dict[str, float] = field(default_factory=dict)
    failed_evaluations: int = 0
    compile_mode: str = "C"
    chain_threads: int = 1
    chain_processes: str = "1"
    prior_bounds: list[dict[str, Any]] = field(default_factory=list)
    nutpie_backend: str = ""
    target_accept: float | None = None
    second_run: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain values for provenance."""
        return {
            "sampler": self.sampler,
            "requested": self.requested,
            "fallback_reason": self.reason,
            "reparameterization": self.reparameterization,
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
            "failed_evaluations": self.failed_evaluations,
            "compile_mode": self.compile_mode,
            "chain_threads": self.chain_threads,
            "chain_processes": self.chain_processes,
            "nutpie_backend": self.nutpie_backend,
            "prior_bounds": list(self.prior_bounds),
            "target_accept": self.target_accept,
            "second_run": dict(self.second_run),
        }


def choose_sampler(requested: str | None) -> tuple[str, str]:
    """The sampler to run for ``requested`` and, if different, why.

    Examples
    --------
    >>> choose_sampler("smc")
    ('smc', '')
    """
    check_sampler(requested)
    requested = requested or "nutpie"
    if requested == "nutpie" and importlib.util.find_spec("nutpie") is None:
        return "pymc", "nutpie is not installed (pip install nutpie)"
    return requested, ""


@contextlib.contextmanager
def one_blas_thread():
    """Limit BLAS to one thread inside the block (no-op without threadpoolctl)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def sample_posterior(
    model: pm.Model,
    *,
    sampler: str | None = None,
    draws: int = 1000,
    tune: int = 1000,
    chains: int = 4,
    cores: int | None = None,
    target_accept: float | None = None,
    random_seed: int | None = None,
    progressbar: bool = False,
    reparameterize: bool = True,
    starts: Sequence[Mapping[str, Any]] = (),
    mode: str | None = None,
    sample_kwargs: Mapping[str, Any] | None = None,
    variance_pairs: Sequence[Sequence[str]] = (),
    scale_parameters: Sequence[str] = (),
    space: ValueSpace | None = None,
    before_sampling: Callable[..., None] | None = None,
    default_target_accept: float = 0.9,
) -> tuple[az.InferenceData, SamplingReport]:
    """Sample ``model``'s posterior; returns the draws and what ran.

    Parameters
    ----------
    model : pymc.Model
    sampler : {"nutpie", "pymc", "smc"}, optional
        Default ``"nutpie"``.
    draws, tune, chains, cores, random_seed, progressbar :
        The usual sampler settings (``cores`` defaults to :func:`default_cores`; it sets
        PyMC's and SMC's processes and nutpie's threads on the native path; through
        the Python callback nutpie's chains share one thread, see
        :attr:`SamplingReport.chain_threads`).
    target_accept : float, optional
        NUTS target acceptance; default ``default_target_accept``, raised to
        :data:`CURVED_TARGET_ACCEPT` when the plan is curved (:func:`target_accept_for`).
    default_target_accept : float
        The default when ``target_accept`` is not given.
    reparameterize : bool
        Find the mode and whiten the sampling coordinates (NUTS samplers only).
    starts : sequence of dict
        Extra optimiser starts, ``{parameter name: value}`` in the user's units.
    mode : str, optional
        PyTensor compile mode of the log density.  Default: NUMBA (2–3× faster per
        evaluation than the C backend on the beam models, and it compiles sooner from
        empty caches), or the C backend when NUMBA cannot compile or run the model; the
        report says which ran.
    sample_kwargs : dict, optional
        Extra keywords for :func:`pymc.sample` / :func:`pymc.sample_smc`, or for
        :func:`nutpie.sample` (e.g. ``maxdepth``, ``low_rank_modified_mass_matrix``).
    variance_pairs : sequence of (str, str) or (str, str, kind)
        Parameters whose variances add up in the likelihood (σ_obs next to an iid
        discrepancy sd, or to a log-variance's intercept with kind ``"log_variance"``);
        with ``reparameterize`` they are sampled as total sd and log ratio
        (:func:`variance_shares`).
    scale_parameters : sequence of str
        A discrepancy's scales (:meth:`~kohpymc.discrepancy.base.Discrepancy.scale_parameters`);
        with ``reparameterize`` a funnel between one of them and the rest is followed
        (:func:`kohpymc.scale_funnel.scale_funnel_plan`).
    space : ValueSpace, optional
        ``value_space(model)`` compiled earlier, to sample without compiling again (e.g.
        many data sets swapped into one model's shared variables); default: compile now.
    before_sampling : callable, optional
        Called as ``before_sampling(space, reparam, settings)`` after the mode is found
        and before the NUTS sampler starts (``settings``: draws, tune, chains, cores,
        seed, sampler, target_accept), e.g. :class:`kohpymc.presampling.PreSampling`;
        its time is ``timings["presampling"]``.

    Returns
    -------
    idata : arviz.InferenceData
        ``posterior`` (the model's free parameters and deterministics) and
        ``sample_stats``.
    report : SamplingReport

    Examples
    --------
    >>> import pymc as pm
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu", 0.0, 10.0)
    ...     _ = pm.Normal("y", mu, 1.0, observed=[1.0, 2.0])
    >>> idata, report = sample_posterior(model, draws=200, tune=200, chains=2,
    ...                                  random_seed=1)  # doctest: +SKIP
    >>> report.sampler, report.reparameterization["kind"]  # doctest: +SKIP
    ('nutpie', 'affine')
    """
    name, reason = choose_sampler(sampler)
    report = SamplingReport(name, sampler or "nutpie", reason)
    cores = default_cores(chains) if cores is None else cores
    seed = 0 if random_seed is None else int(random_seed)
    kwargs = dict(sample_kwargs or {})
    if kwargs.get("initvals") is not None and name != "smc":
        starts = [*starts, dict(kwargs["initvals"])]
        if name == "nutpie":
            kwargs.pop("initvals")
    settings = dict(draws=draws, tune=tune, chains=chains, cores=cores, seed=seed)
    with one_blas_thread():
        if name == "smc":
            return _run_smc(model, settings, kwargs, progressbar), report
        start = time.perf_counter()
        space = _compile(model, space, mode, report)
        shares = variance_shares(space, variance_pairs)
        reparam = _plan(space, starts, seed, reparameterize, report, shares, scale_parameters)
        requested_target_accept = target_accept
        target_accept = target_accept_for(reparam, target_accept, default_target_accept)
        report.target_accept = target_accept
        if before_sampling is not None:
            begin = time.perf_counter()
            before_sampling(
                space, reparam, {**settings, "sampler": name, "target_accept": target_accept}
            )
            report.timings["presampling"] = time.perf_counter() - begin
        report_phase("sampling")
        failures: list[str] = []
        run = (space, reparam, settings, target_accept, progressbar, kwargs)
        begin = time.perf_counter()
        idata = _run_nuts(model, name, run, failures, report)
        fixed = requested_target_accept is not None
        idata = _second_run(model, name, run, idata, failures, report, began=begin, fixed=fixed)
        report.timings["sampling"] = time.perf_counter() - start - sum(report.timings.values())
        _report_rate(settings, report.timings["sampling"])
        _add_observed_data(idata, model)
        _check_bounds(space, idata, report)
        if failures:
            report.failed_evaluations = len(failures)
            report.reparameterization.setdefault("warnings", []).append(
                f"{len(failures)} log-density evaluation(s) failed during sampling and were "
                f"treated as zero density (first: {failures[0]})"
            )
        return idata, report


#: what both NUTS runners take: space, plan, settings, target_accept, progressbar, kwargs
_NutsRun = tuple[ValueSpace, Reparameterization | None, dict[str, Any], float, bool, dict[str, Any]]


def default_cores(chains: int) -> int:
    """The cores a calibration samples on unless told: one per chain, up to those it may use.

    Those it may use: the CPUs this process may run on, or in a Dask worker the worker's
    threads (with one single-threaded worker per core, a formulation's chains then take
    turns on their worker instead of competing with the other workers' chains).

    Examples
    --------
    >>> 1 <= default_cores(4) <= 4
    True
    """
    return max(1, min(chains, _worker_threads() or _usable_cpus()))


def _usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _worker_threads() -> int | None:
    """The threads of the Dask worker this runs in, or None outside one."""
    try:
        from distributed import get_worker

        return int(get_worker().state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return None


def _compile(
    model: pm.Model, space: ValueSpace | None, mode: str | None, report: SamplingReport
) -> ValueSpace:
    """``model``'s value space, compiled now unless the caller's; its time in the report."""
    start = time.perf_counter()
    report_phase("compiling")
    if space is None:
        space = _compiled_space(model, mode, report)
    elif space.model is not model:
        raise ValueError("space must be value_space(model) of the model being sampled")
    else:
        report.compile_mode = "compiled by the caller"
    report.timings["compile"] = time.perf_counter() - start
    return space


def _run_nuts(
    model: pm.Model, name: str, run: _NutsRun, failures: list[str], report: SamplingReport
) -> az.InferenceData:
    """Sample with nutpie when chosen, else (or when it fails: reason recorded) PyMC's NUTS.

    ``run`` is ``(space, reparam, settings, target_accept, progressbar, kwargs)``.
    """
    if name == "nutpie":
        try:
            return _run_nutpie(*run, failures, report)
        # nutpie's Rust panics arrive as pyo3's PanicException, a BaseException
        except BaseException as err:  # noqa: BLE001 - any failure falls back
            if isinstance(err, KeyboardInterrupt | SystemExit | GeneratorExit):
                raise
            report.sampler = "pymc"
            first_line = (str(err).splitlines() or [""])[0][:300]
            report.reason = f"nutpie failed ({type(err).__name__}: {first_line})"
    return _run_pymc(model, *run)


def _second_run(
    model: pm.Model,
    name: str,
    run: _NutsRun,
    first: az.InferenceData,
    failures: list[str],
    report: SamplingReport,
    *,
    began: float,
    fixed: bool,
) -> az.InferenceData:
    """The draws of ``run``, or of a second run when the first's chains show trouble.

    :func:`kohpymc.second_run.plan_second_run` decides (``began``: when the first run
    began; ``fixed``: whether the caller set its target); the second run's draws are kept
    (``failures`` then its failed evaluations) and both runs are in ``report.second_run``.
    """
    first_setup = {k: report.timings.get(k, 0.0) for k in _RUN_SETUP}
    seconds = time.perf_counter() - began - sum(first_setup.values())
    space, reparam, settings, target_accept, progressbar, kwargs = run
    names = [rv.name for rv in model.free_RVs]
    change = plan_second_run(
        first, names, target_accept=target_accept, target_fixed=fixed,
        tune=settings["tune"], draws=settings["draws"], seconds=seconds,
    )  # fmt: skip
    if change is None:
        return first
    report_phase(f"sampling again ({'; '.join(change.reasons)})")
    failures.clear()  # the second run's draws are the result
    changed = {**settings, "draws": change.draws}
    second = _run_nuts(
        model, name, (space, reparam, changed, change.target_accept, progressbar, dict(kwargs)),
        failures, report,
    )  # fmt: skip
    report.second_run = {
        "reasons": change.reasons,
        "target_accept": [target_accept, change.target_accept],
        "draws": [settings["draws"], change.draws],
        "divergences": [n_divergences(first) or 0, n_divergences(second) or 0],
        "smallest_ess_bulk": [round(change.first_ess), round(mixing(second, names)[0])],
        "first_sampling_s": round(seconds, 3),
    }
    for key, value in first_setup.items():  # both runs' set-up, not counted as sampling
        report.timings[key] = report.timings.get(key, 0.0) + value
    report.target_accept = change.target_accept
    return second


#: timings of a NUTS run that are set-up, not sampling (the native density's compile and
#: the map of the draws to the user's parameters)
_RUN_SETUP = ("native_compile", "expand")


def target_accept_for(
    reparam: Reparameterization | None, requested: float | None, default: float = 0.9
) -> float:
    """NUTS target acceptance: ``requested``, else ``default``, at least 0.95 if curved.

    A plan is curved when its map follows a ridge fitted at a few points
    (``reparam.curved``); then the default is raised to :data:`CURVED_TARGET_ACCEPT`.

    Examples
    --------
    >>> target_accept_for(None, None)
    0.9
    >>> target_accept_for(None, 0.8)
    0.8
    """
    if requested is not None:
        return float(requested)
    curved = reparam is not None and reparam.curved
    return max(default, CURVED_TARGET_ACCEPT) if curved else float(default)


def _check_bounds(space: ValueSpace, idata: az.InferenceData, report: SamplingReport) -> None:
    """Record and warn about parameters whose draws lie against a prior bound."""
    hits = hits_in_draws(space, idata["posterior"])
    report.prior_bounds = [hit.to_dict() for hit in hits]
    warn_hits(hits, "in the posterior draws")


def _report_rate(settings: Mapping[str, Any], seconds: float) -> None:
    """The sampling rate (warm-up included) for the progress display."""
    total = (settings["draws"] + settings["tune"]) * settings["chains"]
    report_phase("after sampling")
    report_note(f"{total / max(seconds, 1e-9):.0f} draws/s")


def _user_starts(space: ValueSpace, starts: Sequence[Mapping[str, Any]]) -> list[np.ndarray]:
    """User-unit starting points as value-space vectors (missing entries: initial point)."""
    model = space.model
    out = []
    for start in starts:
        point = space.split(space.initial.copy())
        for rv, value_name in zip(model.free_RVs, space.names, strict=True):
            if rv.name not in start:
                continue
            value = transformed_value(model, rv, start[rv.name])
            point[value_name] = np.broadcast_to(value, point[value_name].shape)
        out.append(space.join(point))
    return out


def variance_shares(space: ValueSpace, pairs: Sequence[Sequence[str]]) -> VarianceShare | None:
    """Value-space indices of ``(σ_a, b[, kind])`` pairs for :class:`VarianceShare`.

    ``σ_a`` must be a free, scalar, log-transformed parameter; ``b`` a scalar
    log-transformed sd (kind ``"sd"``, the default) or the coefficients of a log-variance
    (kind ``"log_variance"``: its first entry, untransformed).  Pairs naming anything
    else (e.g. σ_obs when the noise sd is known) are left out.

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     a = pm.HalfNormal("a", 1.0)
    ...     b = pm.HalfNormal("b", 1.0)
    ...     _ = pm.Normal("y", 0.0, pm.math.sqrt(a**2 + b**2), observed=[1.0, -1.0])
    >>> variance_shares(value_space(model), [("a", "b")]).pairs
    ((0, 1, 1.0),)
    """
    first: dict[str, tuple[int, int, str]] = {}  # name -> (flat index, size, transform)
    start = 0
    for rv, shape in zip(space.model.free_RVs, space.shapes, strict=True):
        size = int(np.prod(shape, dtype=int))
        first[rv.name] = (start, size, space.transforms[start] if size else "")
        start += size
    found, names = [], []
    for a, b, *kind in pairs:
        scale = 2.0 if kind and kind[0] == "log_variance" else 1.0
        wanted_b = ("identity", None) if scale == 2.0 else ("log", 1)
        if a not in first or b not in first or a == b or first[a][1:] != (1, "log"):
            continue
        index_b, size_b, transform_b = first[b]
        if transform_b != wanted_b[0] or (wanted_b[1] is not None and size_b != wanted_b[1]):
            continue
        found.append((first[a][0], index_b, scale))
        names.append((a, b))
    if not found:
        return None
    return VarianceShare(tuple(found), tuple(names))


def _plan(
    space: ValueSpace,
    starts: Sequence[Mapping[str, Any]],
    seed: int,
    reparameterize: bool,
    report: SamplingReport,
    shares: VarianceShare | None = None,
    scales: Sequence[str] = (),
) -> Reparameterization | None:
    if not reparameterize:
        report.reparameterization = {"kind": "none", "reason": "reparameterize=False"}
        return None
    begin = time.perf_counter()
    reparam = plan(space, _user_starts(space, starts), seed=seed, shares=shares)
    reparam = funnel_plan(space, reparam) or scale_funnel_plan(space, reparam, scales) or reparam
    report.timings["mode_and_laplace"] = time.perf_counter() - begin
    report.reparameterization = reparam.to_dict()
    return reparam


def _compiled_space(model: pm.Model, mode: str | None, report: SamplingReport) -> ValueSpace:
    """``value_space(model)`` in ``mode``; by default NUMBA, else the C backend.

    NUMBA compiles on the first call, so the default evaluates once at the initial point;
    when that fails and the C backend evaluates, the C backend is used and the report
    says why.  (A failure of both is the model's own, raised later where it is explained.)
    """
    if mode is not None:
        report.compile_mode = "C" if mode == "FAST_RUN" else mode
        return value_space(model, mode=mode)
    try:
        space = value_space(model, mode="NUMBA")
        space.logp_dlogp(space.initial)
    except Exception as err:  # noqa: BLE001 - decided by whether the C backend runs
        fallback = value_space(model)
        point = _regular_value(fallback)
        if point is None:
            raise
        if point is not fallback.initial and np.isfinite(space.logp_dlogp_or_nan(point)[0]):
            report.compile_mode = "NUMBA"  # the initial point is singular, not NUMBA
            return space
        first_line = (str(err).splitlines() or [""])[0][:200]
        report.compile_mode = f"C (NUMBA failed: {type(err).__name__}: {first_line})"
        return fallback
    report.compile_mode = "NUMBA"
    return space


def _regular_value(space: ValueSpace) -> np.ndarray | None:
    """The initial point or one next to it where the log density is finite (else None).

    The points are :func:`~kohpymc.value_space.nudged`'s.
    """
    for point in nudged(space.initial):
        if np.isfinite(space.logp_dlogp_or_nan(point)[0]):
            return point
    return None


def _run_nutpie(
    space: ValueSpace,
    reparam: Reparameterization | None,
    settings: dict[str, Any],
    target_accept: float,
    progressbar: bool,
    kwargs: dict[str, Any],
    failures: list[str],
    report: SamplingReport,
) -> az.InferenceData:
    """Nutpie's NUTS on the sampling coordinates ``z``, natively when the model allows.

    The native path (:func:`kohpymc.native.native_model`) runs the chains on
    ``settings["cores"]`` threads; when it cannot compile, a Python log density runs,
    each chain alone, the chains split over forked processes
    (:func:`kohpymc.chain_processes.sample_chains`), and ``report.nutpie_backend`` says
    why.  There, a log-density
    evaluation that raises (e.g. a physics function overflowing far in the tails)
    counts as zero density; its message is appended to ``failures``.
    """
    import nutpie

    from kohpymc.native import expand_draws

    mapping = reparam if reparam is not None else _identity_map(space)
    coords, dims = _coords_and_dims(space)
    compiled, cores = _native_or_python(space, mapping, settings, failures, report)
    report.chain_threads = cores

    def sample(chains: int, seed: int, progress: bool) -> GroupResult:
        known = len(failures)
        with warnings.catch_warnings(), quiet_density_errors():
            warnings.simplefilter("ignore", FutureWarning)
            idata = nutpie.sample(
                compiled,
                draws=settings["draws"],
                tune=settings["tune"],
                chains=chains,
                cores=cores,
                seed=seed,
                progress_bar=progress,
                target_accept=target_accept,
                init_mean=np.zeros(space.ndim),
                save_warmup=False,
                **kwargs,
            )
        return idata, failures[known:]

    if report.nutpie_backend.startswith("python"):  # chains in processes (GIL-bound)
        before = list(failures)  # a forked chain's failures come back in ``found`` only
        idata, found, report.chain_processes = sample_chains(
            lambda seed, progress: sample(1, seed, progress),
            settings["chains"], settings["cores"], settings["seed"], progressbar,
        )  # fmt: skip
        failures[:] = before + found
    else:
        idata, _ = sample(settings["chains"], settings["seed"], progressbar)
    begin = time.perf_counter()
    idata = expand_draws(idata, space, mapping, coords, dims)
    report.timings["expand"] = time.perf_counter() - begin
    return idata


def _native_or_python(
    space: ValueSpace,
    mapping: Reparameterization,
    settings: Mapping[str, Any],
    failures: list[str],
    report: SamplingReport,
) -> tuple[Any, int]:
    """Nutpie's model of ``z`` and its number of threads: native, else the Python callback.

    The Python callback runs on one thread: the chains' calls go through one lock and
    the GIL, so a second thread only adds contention (beam M4: 28.7 s on two threads,
    18.1 s on one).
    """
    from kohpymc.native import native_model

    initial_point = _initial_point_fn(space.ndim, mapping.kind)
    begin = time.perf_counter()
    try:
        compiled = native_model(space, mapping, initial_point)
    except Exception as err:  # noqa: BLE001 - any failure falls back, with the reason
        first_line = (str(err).splitlines() or [""])[0][:300]
        report.nutpie_backend = f"python (native: {type(err).__name__}: {first_line})"
        return _nutpie_model(space, mapping, failures, initial_point), 1
    finally:
        report.timings["native_compile"] = time.perf_counter() - begin
    report.nutpie_backend = "numba-native"
    return compiled, max(1, int(settings["cores"]))


def _initial_point_fn(ndim: int, kind: str) -> Callable[[int], np.ndarray]:
    """Each chain's start ``z``: uniform within half a posterior sd of the mode.

    Whitened coordinates have unit scale; in PyMC's own (``kind="none"``) ±1.

    Examples
    --------
    >>> _initial_point_fn(2, "affine")(1).shape
    (2,)
    """
    jitter = 1.0 if kind == "none" else 0.5

    def initial_point(seed):
        return np.random.default_rng(seed).uniform(-jitter, jitter, size=ndim)

    return initial_point


def _identity_map(space: ValueSpace) -> Reparameterization:
    """``z = v − v₀`` around PyMC's initial point (``reparameterize=False``)."""
    identity = Coordinates.identity(space.ndim)
    return Reparameterization("none", space.initial, np.eye(space.ndim), identity, "")


def _nutpie_model(
    space: ValueSpace,
    mapping: Reparameterization,
    failures: list[str],
    initial_point: Callable[[int], np.ndarray],
):
    """Nutpie's model of ``z`` through Python: log density and starts; it keeps ``z``.

    The kept draws are mapped to the user's parameters after sampling, all at once
    (:func:`kohpymc.native.expand_draws`), as on the native path.
    """
    from nutpie.compiled_pyfunc import from_pyfunc

    from kohpymc.native import KEPT_DRAWS

    # Chains run in threads that take the GIL for every call anyway; one lock keeps the
    # compiled PyTensor functions (and the OpFromGraph functions inside them, which
    # Function.copy does not duplicate) from being entered by two chains at once.
    lock = threading.Lock()

    def make_logp():
        def logp(z, **_):
            with lock:
                try:
                    value, grad = mapping.logp_dlogp(space, z)
                except Exception as err:  # noqa: BLE001 - reported after sampling
                    failures.append(f"{type(err).__name__}: {str(err).splitlines()[0]}")
                    return -np.inf, np.zeros(space.ndim)
            return value, np.asarray(grad, dtype=float, order="C")

        return logp

    def make_expand(seed1, seed2, chain):
        def expand(z, **_):
            return {KEPT_DRAWS: np.array(z, dtype=float)}

        return expand

    return from_pyfunc(
        space.ndim,
        make_logp,
        make_expand,
        [np.dtype("float64")],
        [(space.ndim,)],
        [KEPT_DRAWS],
        make_initial_point_fn=initial_point,
    )


def _add_observed_data(idata: az.InferenceData, model: pm.Model) -> None:
    """The ``observed_data`` group that :func:`pymc.sample` would have written."""
    from pymc.backends.arviz import find_observations

    if "observed_data" in idata.groups():
        return
    observed = find_observations(model)
    if not observed:
        return
    dims = {k: list(model.named_vars_to_dims.get(k, ())) for k in observed}
    coords = {
        d: np.asarray(model.coords[d])
        for ds in dims.values()
        for d in ds
        if model.coords.get(d) is not None
    }
    extra = az.from_dict(observed_data=observed, dims=dims, coords=coords)
    idata.add_groups(observed_data=extra.observed_data)


def _coords_and_dims(space: ValueSpace) -> tuple[dict[str, Any], dict[str, tuple[str, ...]]]:
    """The model's coords (as ``pandas.Index``, which nutpie needs) and dims."""
    import pandas as pd

    model = space.model
    dims = {
        name: tuple(model.named_vars_to_dims[name])
        for name in space.expanded_names
        if name in model.named_vars_to_dims
    }
    coords = {}
    for name, values in model.coords.items():
        if values is None:
            values = pd.RangeIndex(int(model.dim_lengths[name].eval()))
        coords[name] = pd.Index(values)
    return coords, dims


def _run_pymc(
    model: pm.Model,
    space: ValueSpace,
    reparam: Reparameterization | None,
    settings: dict[str, Any],
    target_accept: float,
    progressbar: bool,
    kwargs: dict[str, Any],
) -> az.InferenceData:
    """PyMC's NUTS, started at the mode when one was found."""
    if reparam is not None and reparam.mode is not None and "initvals" not in kwargs:
        start = space.split(reparam.mode.value)
        kwargs["initvals"] = _constrained_point(space, start)
    with model:
        return pm.sample(
            draws=settings["draws"],
            tune=settings["tune"],
            chains=settings["chains"],
            cores=settings["cores"],
            random_seed=settings["seed"],
            target_accept=target_accept,
            progressbar=progressbar,
            compute_convergence_checks=False,
            idata_kwargs={"log_likelihood": False},
            **kwargs,
        )


def _constrained_point(space: ValueSpace, point: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Value-space point -> initvals in the user's units (PyMC transforms them back)."""
    expanded = space.expand(space.join(dict(point)))
    return {rv.name: expanded[rv.name] for rv in space.model.free_RVs}


def _run_smc(
    model: pm.Model, settings: dict[str, Any], kwargs: dict[str, Any], progressbar: bool
) -> az.InferenceData:
    """PyMC's SMC with the random-walk MH kernel; convergence is checked by the caller.

    PyMC's default independent-proposal kernel (IMH) returned a posterior three times too
    wide, with r̂ 1.05 between runs, on y = a·exp(−b·x) with unknown noise (25 rows, corr(a,
    b) ≈ 0.9): a = 1.997 ± 0.025 against NUTS's 1.998 ± 0.008; the MH kernel, whose
    proposals follow the particles' covariance, gave 1.998 ± 0.008, r̂ 1.00.  A ``kernel``
    in ``sample_kwargs`` is used instead.
    """
    kwargs = {"kernel": pm.smc.kernels.MH, **kwargs}
    with model:
        idata = pm.sample_smc(
            draws=settings["draws"],
            chains=settings["chains"],
            cores=settings["cores"],
            random_seed=settings["seed"],
            progressbar=progressbar,
            compute_convergence_checks=False,
            **kwargs,
        )
    return _smc_stats_per_stage(idata)


def _smc_stats_per_stage(idata: az.InferenceData) -> az.InferenceData:
    """SMC's statistics as floats over a ``stage`` dimension, so NetCDF can store them.

    PyMC gives one value per tempering stage as ``object`` arrays (β mixing floats and the
    final int 1, NaN-padded where a chain took fewer stages) over a dimension named
    ``draw`` that is not the posterior's; ``to_netcdf`` refused them ("unable to infer
    dtype on variable 'beta'"), so a study with ``sampler = "smc"`` lost every result.
    """
    if "sample_stats" not in idata.groups():
        return idata
    stats = idata["sample_stats"]
    if any(_ragged(v.values) for v in stats.data_vars.values()):
        stats = _padded_stages(stats)
    stats = stats.assign({k: v.astype(float) for k, v in stats.data_vars.items()})
    if "draw" in stats.dims:
        stats = stats.rename({"draw": "stage"})
    idata["sample_stats"] = stats
    return idata


def _ragged(values: np.ndarray) -> bool:
    """Whether ``values`` holds one sequence per cell (chains that took different stages)."""
    return values.dtype == object and all(np.ndim(cell) == 1 for cell in values.ravel())


def _padded_stages(stats: Any) -> Any:
    """``(chain, stage)`` floats, NaN-padded, from PyMC's one-list-per-chain statistics.

    When the chains took different numbers of tempering stages (11 and 12 on a bimodal
    pharmacokinetic posterior with 4000 particles) PyMC stores each statistic as a
    ``(1, chains)`` object array of lists, which no float cast takes ("setting an array
    element with a sequence"), and the whole calibration failed after sampling.
    """
    import xarray as xr

    def padded(values: np.ndarray) -> np.ndarray:
        rows = [np.asarray(cell, dtype=float) for cell in values.ravel()]
        out = np.full((len(rows), max(row.size for row in rows)), np.nan)
        for i, row in enumerate(rows):
            out[i, : row.size] = row
        return out

    data = {k: (("chain", "stage"), padded(v.values)) for k, v in stats.data_vars.items()}
    return xr.Dataset(data, attrs=stats.attrs)
