r"""Between finding the posterior mode and sampling: identifiability there, and the run's cost.

:func:`kohpymc.calibrate` checks identifiability at the prior centre before it compiles
anything.  For nonlinear physics that point may say little: a threshold beyond the data
or a transient over before the first measurement leaves parameters without effect at
the centre that the data inform well near the fit.  Once the sampler has found the
posterior mode (:func:`kohpymc.reparameterization.plan`), :class:`PreSampling`, called
by :func:`kohpymc.sampling.sample_posterior` just before the sampler starts,

1. checks whether the mode lies against a prior bound
   (:func:`kohpymc.prior_bounds.hits_at_mode`), warning with a
   :class:`~kohpymc.prior_bounds.PriorBoundWarning` for each parameter that does;
2. maps the mode to the user's parameters and repeats the Taylor check there
   (:func:`kohpymc.identifiability.check_at_point`), warning with an
   :class:`~kohpymc.identifiability.IdentifiabilityWarning` that names the confounded
   combination (rank deficit) or the combination the data inform (ill-conditioned);
3. estimates the sampling time (:func:`estimate_cost`): seconds per log-density plus
   gradient evaluation at the mode, times leapfrog steps per draw, times iterations and
   chains, and warns with a :class:`SlowSamplingWarning` when the estimate exceeds a
   threshold (default 10 minutes), saying why: expensive physics (an emulator helps),
   long trajectories on a ridge (named by the mode check), a gradient that disagrees
   with finite differences or separated modes (``sampler="smc"`` needs no gradient).

Gradient evaluations per iteration
----------------------------------
The Laplace geometry at the mode does not predict them where it matters: on a curved
ridge (``y = a·b·x`` with bounded priors) the whitened posterior looks like a standard
normal at the mode (a leapfrog probe there turns back after ~4 steps) while NUTS needs
~180 steps per draw once its mass matrix has adapted to the whole ridge.  So the probe
is the sampler itself: :func:`probe_steps` runs one chain of nutpie's NUTS in the
sampling coordinates, :data:`PROBE_ITERATIONS` warm-up iterations then
:data:`DRAWS_PROBE` draws (at most ``probe_s`` seconds: 10–20 s from
:class:`PreSampling`), and counts the evaluations of every iteration.  The estimate
charges each chain the probe's finished warm-up iterations as counted (they are a prefix
of the chain's own warm-up) and the rest of the run at the probe's later rate (its
draws, or the second half of a warm-up cut short by the time budget).  A posterior whose
trajectories keep growing as the mass matrix adapts to a long curved ridge is
underestimated (``y = a·b·x``: 50–90 steps per draw after the probe's warm-up, 180 in a
2 × (100 + 100) run).  Without nutpie the Laplace
correlation condition number ``κ`` gives ``4·√κ`` steps (four for a standard normal),
and a plan without a positive-definite Hessian (a flat direction) the tree-depth limit
(1023 steps).  Chains share one lock around the Python log density in nutpie, so they
evaluate one at a time (``parallel=1``).

The estimate's parts, the mode check and the bounds found are recorded in the result's
provenance.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kohpymc.diagnostics import SlowSamplingWarning
from kohpymc.identifiability import (
    IdentifiabilityReport,
    IdentifiabilityWarning,
    check_at_point,
    ridge_text,
)
from kohpymc.prior_bounds import BoundHit, hits_at_mode, warn_hits
from kohpymc.reparameterization import Coordinates, Reparameterization
from kohpymc.value_space import ValueSpace
from kohpymc.warning_filters import warn_user

__all__ = [
    "SLOW_SAMPLING_S",
    "CostEstimate",
    "PreSampling",
    "SlowSamplingWarning",
    "estimate_cost",
    "mode_parameters",
    "probe_steps",
    "slow_reasons",
]

#: estimated sampling time (seconds) above which :class:`SlowSamplingWarning` is issued
SLOW_SAMPLING_S = 600.0
#: warm-up iterations of the probe that counts gradient evaluations per iteration
PROBE_ITERATIONS = 50
#: draws of the probe after its warm-up (a short warm-up can leave long trajectories)
DRAWS_PROBE = 10
#: NUTS's default tree-depth limit (nutpie and PyMC: depth 10, 1023 steps)
MAX_STEPS = 1023
#: seconds per evaluation above which the physics is called expensive
EXPENSIVE_S = 1e-3
#: steps per draw above which trajectories are called long
LONG_STEPS = 32


@dataclass
class CostEstimate:
    """Estimated sampling time and its parts.

    Attributes
    ----------
    seconds_per_evaluation : float
        One log density plus gradient, timed at the mode.
    steps_per_draw : float
        Expected NUTS leapfrog steps (gradient evaluations) per draw.
    steps_from : str
        ``"probe"``, ``"laplace"`` (condition number) or ``"flat"`` (depth limit).
    iterations : int
        Warm-up plus draws, over all chains.
    seconds : float
        The estimate.
    threshold_s : float or None
        Warn above this.
    reasons : list of str
        Why the run is slow (filled when the estimate exceeds the threshold).

    Examples
    --------
    >>> cost = CostEstimate(0.0066, 60.0, "probe", 8000, 3168.0, threshold_s=600.0)
    >>> cost.exceeds, cost.summary()[:7]
    (True, '~53 min')
    """

    seconds_per_evaluation: float
    steps_per_draw: float
    steps_from: str
    iterations: int
    seconds: float
    threshold_s: float | None = None
    reasons: list[str] = field(default_factory=list)

    @property
    def exceeds(self) -> bool:
        """Whether the estimate is above the threshold."""
        return self.threshold_s is not None and self.seconds > self.threshold_s

    def to_dict(self) -> dict[str, Any]:
        """Plain values for provenance."""
        return {
            "seconds_per_evaluation": float(self.seconds_per_evaluation),
            "steps_per_draw": float(self.steps_per_draw),
            "steps_from": self.steps_from,
            "iterations": int(self.iterations),
            "estimated_seconds": float(self.seconds),
            "threshold_s": self.threshold_s,
            "exceeds": self.exceeds,
            "reasons": list(self.reasons),
        }

    def summary(self) -> str:
        """The estimate and its parts in one line."""
        return (
            f"~{_duration(self.seconds)} ({self.iterations} iterations incl. warm-up × "
            f"~{self.steps_per_draw:.0f} leapfrog steps × "
            f"{1e3 * self.seconds_per_evaluation:.3g} ms per log-density+gradient evaluation)"
        )


def _first_line(err: BaseException) -> str:
    """``TypeName: first line of the message`` (at most 300 characters)."""
    return f"{type(err).__name__}: {(str(err).splitlines() or [''])[0][:300]}"


def _duration(seconds: float) -> str:
    """``"45 s"``, ``"12 min"``, ``"3.1 h"``."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def mode_parameters(space: ValueSpace, reparam: Reparameterization | None) -> dict[str, Any]:
    """The posterior mode in the user's parameters (empty without a mode).

    The mode of the density in PyMC's value space (where the sampler runs), which
    includes the transforms' Jacobians: for a positive parameter it is the mode of
    ``log p`` in ``ln x``, not in ``x``.

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.reparameterization import plan
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu", 0.0, 10.0)
    ...     _ = pm.Normal("y", mu, 1.0, observed=[1.0, 2.0])
    >>> space = value_space(model)
    >>> round(float(mode_parameters(space, plan(space, seed=1))["mu"]), 3)  # 3 / (2 + 1/100)
    1.493
    """
    if reparam is None or reparam.mode is None:
        return {}
    expanded = space.expand(reparam.mode.value)
    names = {rv.name for rv in space.model.free_RVs}
    return {k: v for k, v in expanded.items() if k in names}


def _timed(logp_grad: Callable, z: np.ndarray, n: int) -> float:
    """Median seconds per call of ``logp_grad`` at ``z`` (after one untimed call)."""
    logp_grad(z)
    times = []
    for _ in range(n):
        begin = time.perf_counter()
        logp_grad(z)
        times.append(time.perf_counter() - begin)
    return float(np.median(times))


def probe_steps(
    logp_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
    ndim: int,
    *,
    iterations: int = 50,
    seconds: float = 20.0,
    target_accept: float = 0.8,
    seed: int = 0,
) -> tuple[float, float, int]:
    """Gradient evaluations per NUTS iteration, from a short run of nutpie's NUTS.

    One chain of ``iterations`` warm-up iterations and :data:`DRAWS_PROBE` draws from
    near ``z = 0`` (within ±0.5, as the sampler's chains start), stopped after
    ``seconds``; the evaluations are counted in each phase.  Early warm-up (small step
    sizes, a mass matrix not yet adapted) costs more per iteration than later ones.

    Parameters
    ----------
    logp_grad : callable
        ``z -> (log density, gradient)`` in the sampling coordinates.
    ndim : int
    iterations : int
        Warm-up iterations of the probe.
    seconds : float
        Time budget; a probe stopped early gives the evaluations per iteration so far
        (per started iteration when none finished: a lower bound).
    target_accept : float
    seed : int

    Returns
    -------
    (per warm-up iteration, per later iteration, warm-up iterations finished)
        Later: the draws after the warm-up or, when the time budget ends the probe
        first, the second half of the finished warm-up (NaN with fewer than 8).

    Examples
    --------
    >>> import numpy as np
    >>> warm_up, after, done = probe_steps(lambda z: (-0.5 * z @ z, -z), 3, seed=1)
    >>> 1 <= after <= warm_up <= 16, done
    (True, 50)
    """
    import nutpie

    compiled, evaluations, marks = _counting_model(logp_grad, ndim, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        sampler = nutpie.sample(
            compiled,
            draws=DRAWS_PROBE,
            tune=iterations,
            chains=1,
            cores=1,
            seed=seed,
            progress_bar=False,
            target_accept=target_accept,
            init_mean=np.zeros(ndim),
            blocking=False,
        )
    try:
        sampler.wait(timeout=seconds)
    except TimeoutError:
        sampler.cancel()
    return _rates(list(marks), evaluations[0], iterations)


def _counting_model(logp_grad: Callable, ndim: int, seed: int):
    """Nutpie's model of ``logp_grad`` that counts evaluations and marks each iteration.

    Returns the compiled model, the evaluation counter (a one-element list) and the
    list of the counter's values at the end of each iteration.
    """
    from nutpie.compiled_pyfunc import from_pyfunc

    evaluations = [0]
    marks: list[int] = []

    def make_logp():
        def logp(z, **_):
            evaluations[0] += 1
            value, grad = logp_grad(z)
            if not np.isfinite(value) or not np.all(np.isfinite(grad)):
                return -np.inf, np.zeros(ndim)
            return value, np.asarray(grad, dtype=float, order="C")

        return logp

    def make_expand(seed1, seed2, chain):
        def expand(z, **_):
            marks.append(evaluations[0])
            return {"z": np.array(z, dtype=float)}

        return expand

    rng = np.random.default_rng(seed)
    compiled = from_pyfunc(
        ndim,
        make_logp,
        make_expand,
        [np.dtype("float64")],
        [(ndim,)],
        ["z"],
        make_initial_point_fn=lambda _: rng.uniform(-0.5, 0.5, size=ndim),
    )
    return compiled, evaluations, marks


def _rates(marks: list[int], evaluations: int, iterations: int) -> tuple[float, float, int]:
    """Evaluations per warm-up iteration and per later iteration, from the marks.

    Later: the draws after the warm-up, else the second half of a warm-up cut short
    (NaN with fewer than 8 warm-up iterations finished).  With none finished, the
    evaluations so far stand for the first iteration (a lower bound).
    """
    per = np.diff(np.asarray([0, *marks], dtype=float))
    warm, drawn = per[:iterations], per[iterations:]
    if warm.size == 0:
        return float(max(evaluations, 1)), float("nan"), 0
    if drawn.size:
        later = float(drawn.mean())
    elif warm.size >= 8:
        later = float(warm[warm.size // 2 :].mean())
    else:
        later = float("nan")
    return float(warm.mean()), later, int(warm.size)


def _laplace_steps(reparam: Reparameterization | None) -> tuple[float, str]:
    """Steps per draw from the Laplace geometry, when nutpie cannot probe."""
    cond = float("nan") if reparam is None else reparam.condition_number
    if reparam is not None and reparam.mode is not None and not np.isfinite(cond):
        return float(MAX_STEPS), "flat"
    whitened = reparam is not None and "affine" in reparam.kind
    cond = 1.0 if whitened or not np.isfinite(cond) else max(cond, 1.0)
    return min(float(MAX_STEPS), 4.0 * math.sqrt(cond)), "laplace"


def estimate_cost(
    space: ValueSpace,
    reparam: Reparameterization | None,
    *,
    draws: int,
    tune: int,
    chains: int,
    parallel: int = 1,
    target_accept: float = 0.8,
    threshold_s: float | None = SLOW_SAMPLING_S,
    probe_s: float = 20.0,
    seed: int = 0,
) -> CostEstimate:
    """Estimated NUTS sampling time at the plan's mode (see the module docstring).

    Parameters
    ----------
    space : ValueSpace
    reparam : Reparameterization or None
        The plan from :func:`kohpymc.reparameterization.plan` (None: PyMC's coordinates
        from the initial point).
    draws, tune, chains : int
        The sampler settings.
    parallel : int
        Chains that evaluate the log density at the same time (1 for nutpie's
        Python log density, which chains share under one lock).
    target_accept : float
    threshold_s : float or None
        Stored with the estimate (``exceeds``).
    probe_s : float
        Time budget of the warm-up probe (:func:`probe_steps`); no probe when even
        1023 steps per draw would stay below ``threshold_s`` (the Laplace guess then).
    seed : int

    Returns
    -------
    CostEstimate

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu", 0.0, 10.0)
    ...     _ = pm.Normal("y", mu, 1.0, observed=[1.0, 2.0])
    >>> cost = estimate_cost(value_space(model), None, draws=100, tune=100, chains=2)
    >>> cost.iterations, cost.exceeds, cost.steps_from  # far too cheap to need a probe
    (400, False, 'laplace')
    """
    mapping = reparam if reparam is not None else _identity(space)

    def logp_grad(z):
        return mapping.logp_dlogp(space, z, safe=True)

    per_eval = _timed(logp_grad, np.zeros(space.ndim), 5)
    iterations = chains * (draws + tune)
    share = per_eval / max(1, min(parallel, chains))
    steps, source = _laplace_steps(reparam)
    # a probe only where the tree-depth limit could reach the threshold
    if threshold_s is None or iterations * MAX_STEPS * share > threshold_s:
        early = max(1, min(PROBE_ITERATIONS, tune))
        try:
            warm_up, after, done = probe_steps(
                logp_grad,
                space.ndim,
                iterations=early,
                seconds=probe_s,
                target_accept=target_accept,
                seed=seed,
            )
        except ImportError:
            pass
        else:
            after = warm_up if not np.isfinite(after) else after
            # the probed iterations as counted (a prefix of each chain's warm-up), the
            # rest of the warm-up and the draws at the later rate
            per_chain = done * warm_up + max(draws + tune - done, 0) * after
            steps, source = per_chain / max(draws + tune, 1), "probe"
    seconds = iterations * steps * share
    return CostEstimate(per_eval, steps, source, iterations, seconds, threshold_s)


def _identity(space: ValueSpace) -> Reparameterization:
    """PyMC's coordinates around the initial point."""
    coords = Coordinates.identity(space.ndim)
    return Reparameterization("none", space.initial, np.eye(space.ndim), coords, "")


def slow_reasons(
    cost: CostEstimate, reparam: Reparameterization | None, report: IdentifiabilityReport | None
) -> list[str]:
    """Why a run is slow, each with what to do about it.

    Examples
    --------
    >>> slow_reasons(CostEstimate(0.02, 4.0, "probe", 8000, 900.0), None, None)[0][:36]
    'each log-density+gradient evaluation'
    """
    reasons = []
    if cost.seconds_per_evaluation > EXPENSIVE_S:
        reasons.append(
            f"each log-density+gradient evaluation takes "
            f"{1e3 * cost.seconds_per_evaluation:.3g} ms (the physics model): an emulator "
            "(kohpymc.Emulator) trained on a few hundred runs is far cheaper to sample"
        )
    ridge = ridge_text(report) if report is not None else ""
    if cost.steps_per_draw > LONG_STEPS or ridge:
        geometry = (
            f"the posterior is far from Gaussian at its mode (Laplace score "
            f"{reparam.gaussian_score:.3g}, 0 for a Gaussian)"
            if reparam is not None and np.isfinite(reparam.gaussian_score)
            else "a flat direction at the mode"
        )
        reasons.append(
            f"NUTS needs ~{cost.steps_per_draw:.0f} leapfrog steps per draw; "
            + (f"at the posterior mode {ridge}" if ridge else geometry)
        )
    for text in reparam.warnings if reparam is not None else ():
        if "disagrees with finite differences" in text or "separated modes" in text:
            reasons.append(text)
    if not reasons:
        reasons.append("many iterations: fewer draws or chains would be quicker")
    return reasons


@dataclass
class PreSampling:
    """The hook :func:`kohpymc.calibrate` passes to ``sample_posterior(before_sampling=)``.

    Called with the compiled value space, the plan (mode and whitening) and the sampler
    settings; runs the identifiability check at the mode (when ``plain`` is given) and
    the cost estimate (when ``threshold_s`` is not None), warning on either, and keeps
    the results.

    Attributes
    ----------
    plain : CalibrationModel or None
        The unmarginalized model the Taylor check differentiates (None: no mode check).
    physics : PhysicsModel, optional
        For the structural-or-practical verdict of a deficit in the physics alone.
    inputs : mapping, optional
        The data design.
    label : str
        Names the run in warnings (``"M0 calibration of 'beam'"``).
    threshold_s : float or None
        Warn when the estimated sampling time exceeds this; None: no estimate.
    target_accept : float
    mode : dict
        The posterior mode in the user's parameters (after the call).
    report : IdentifiabilityReport or None
        The check at the mode (after the call).
    cost : CostEstimate or None
        After the call.
    notes : list of str
        Why a part was skipped.
    bounds : list of BoundHit
        Parameters whose mode lies against a prior bound (after the call;
        :mod:`kohpymc.prior_bounds`), each also warned about.

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.sampling import sample_posterior
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu", 0.0, 10.0)
    ...     _ = pm.Normal("y", mu, 1.0, observed=[1.0, 2.0])
    >>> hook = PreSampling(None, threshold_s=1e-9)
    >>> idata, _ = sample_posterior(model, draws=50, tune=50, chains=1,
    ...                             before_sampling=hook)  # doctest: +SKIP
    >>> hook.cost.exceeds  # doctest: +SKIP
    True
    """

    plain: Any
    physics: Any = None
    inputs: Mapping[str, Any] | None = None
    label: str = "calibration"
    threshold_s: float | None = SLOW_SAMPLING_S
    target_accept: float = 0.8
    mode: dict[str, Any] = field(default_factory=dict)
    report: IdentifiabilityReport | None = None
    cost: CostEstimate | None = None
    notes: list[str] = field(default_factory=list)
    bounds: list[BoundHit] = field(default_factory=list)

    def __call__(
        self, space: ValueSpace, reparam: Reparameterization | None, settings: Mapping[str, Any]
    ) -> None:
        """Check the bounds and identifiability at the mode, then estimate the cost."""
        self.mode = mode_parameters(space, reparam)
        if reparam is not None and reparam.mode is not None and reparam.value_sd is not None:
            self.bounds = hits_at_mode(space, reparam.mode.value, reparam.value_sd)
            warn_hits(self.bounds, f"at the posterior mode of {self.label}")
        if self.plain is not None:
            self._check_mode()
        if self.threshold_s is not None and settings.get("sampler", "nutpie") != "smc":
            self._estimate(space, reparam, settings)

    def _check_mode(self) -> None:
        if not self.mode:
            self.notes.append("identifiability at the mode skipped: no mode was found")
            return
        names = {rv.name for rv in self.plain.model.free_RVs}
        point = {k: v for k, v in self.mode.items() if k in names}
        try:
            self.report = check_at_point(
                self.plain, point, physics=self.physics, inputs=self.inputs
            )
        except Exception as err:  # noqa: BLE001 - a check must not stop the calibration
            self.notes.append(f"identifiability at the mode skipped: {_first_line(err)}")
            return
        text = ridge_text(self.report)
        if not text:
            return
        verdict = (
            f"is not identifiable at the posterior mode (rank {self.report.rank} of "
            f"{len(self.report.names)}): "
            if not self.report.identifiable
            else "is practically non-identifiable at the posterior mode: "
        )
        warn_user(f"{self.label} {verdict}{text}", IdentifiabilityWarning)

    def _estimate(self, space, reparam, settings) -> None:
        parallel = 1 if settings.get("sampler", "nutpie") == "nutpie" else settings["cores"]
        try:
            self.cost = estimate_cost(
                space,
                reparam,
                draws=settings["draws"],
                tune=settings["tune"],
                chains=settings["chains"],
                parallel=parallel,
                target_accept=settings.get("target_accept", self.target_accept),
                threshold_s=self.threshold_s,
                probe_s=min(20.0, max(10.0, 0.05 * float(self.threshold_s or 0.0))),
                seed=int(settings.get("seed", 0)),
            )
        # nutpie's Rust panics arrive as pyo3's PanicException, a BaseException
        except BaseException as err:  # noqa: BLE001 - an estimate must not stop the run
            if isinstance(err, KeyboardInterrupt | SystemExit | GeneratorExit):
                raise
            self.notes.append(f"sampling-time estimate skipped: {_first_line(err)}")
            return
        if not self.cost.exceeds:
            return
        self.cost.reasons = slow_reasons(self.cost, reparam, self.report)
        warn_user(
            f"{self.label}: sampling is estimated to take {self.cost.summary()}, above "
            f"{_duration(float(self.threshold_s or 0.0))}. Why: "
            + "; ".join(self.cost.reasons)
            + " (estimated before sampling, which goes ahead; see the module "
            "kohpymc.presampling)",
            SlowSamplingWarning,
        )

    def explaining(self, centre: IdentifiabilityReport | None) -> IdentifiabilityReport | None:
        """The report that explains a flat direction at the mode.

        The check at the mode when it has a rank deficit, else ``centre`` (the check at
        the prior centre).
        """
        if self.report is not None and not self.report.identifiable:
            return self.report
        return centre

    def to_dict(self) -> dict[str, Any]:
        """Plain values for provenance."""
        return {
            "mode": {k: np.asarray(v, float).tolist() for k, v in self.mode.items()},
            "identifiability_at_mode": None if self.report is None else self.report.to_dict(),
            "cost": None if self.cost is None else self.cost.to_dict(),
            "notes": list(self.notes),
            "prior_bounds": [hit.to_dict() for hit in self.bounds],
        }
