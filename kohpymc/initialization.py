r"""Starting points for samplers: a multi-start least-squares fit of the physics model.

A sampler started at the prior centre can be far from the data when the model output
varies over orders of magnitude across the prior, or when the least-squares surface has
several basins.  :func:`multistart_least_squares` fits ``G(x; θ)`` to the data from a
space-filling set of starts and returns the best fit, to pass as ``initvals``:

.. math::

    \hat θ = \arg\min_{θ \in B} \tfrac12 \sum_i \left(\frac{G(x_i; θ) - y_i}{σ}\right)^2,

with ``B`` the search box of :func:`prior_box` (each prior's support, or its central
``coverage`` interval for unbounded priors) and ``σ`` the known noise sd of the data
(else the sd of ``y``).  The model is fitted without discrepancy here, so the fit is a
starting point for a sampler, not an estimate.

Each parameter is mapped linearly onto ``[0, 1]`` over its box, so parameters of very
different magnitudes (``A ~ 1e3``, ``τ ~ 1e-3``) are equally well conditioned for the
trust-region solver (:func:`scipy.optimize.least_squares`, ``"trf"``, 2-point
differences).  The starts are the first points of a scrambled Sobol sequence
(:class:`scipy.stats.qmc.Sobol`).  With ``transform`` each start is first fitted on
transformed outputs (e.g. log currents), which is well scaled where the raw residuals are
dominated by the largest outputs; the best of these is then refined on the raw residuals.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from kohpymc.data import CalibrationData
from kohpymc.physics import PhysicsModel, PhysicsModelError
from kohpymc.priors import Prior

__all__ = ["MultistartResult", "multistart_least_squares", "prior_box"]

#: residual given to rows where the model failed or returned NaN/inf
_BAD = 1e100
#: prior mean ± this many sd is the box of a custom prior (no quantiles known)
_CUSTOM_SDS = 3.0


@dataclass(frozen=True)
class MultistartResult:
    """Outcome of :func:`multistart_least_squares`.

    Attributes
    ----------
    params : dict
        Best fit, parameter name -> value, in the physics model's parameter order.
    cost : float
        ``½ Σ ((G - y) / σ)²`` at :attr:`params`.
    names : tuple of str
        Parameter names (the columns of the arrays below).
    starts : numpy.ndarray
        ``(k, p)`` starting points, natural units.
    fits : numpy.ndarray
        ``(k, p)`` local optimum reached from each start (of the transformed fit when a
        ``transform`` was given).
    start_costs : numpy.ndarray
        ``(k,)`` cost at each of :attr:`fits` (transformed residuals when a ``transform``
        was given).
    lower, upper : numpy.ndarray
        The search box (after the ``margin``).
    """

    params: dict[str, float]
    cost: float
    names: tuple[str, ...]
    starts: np.ndarray
    fits: np.ndarray
    start_costs: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


def _quantile_box(prior: Prior, coverage: float) -> tuple[float, float]:
    if prior.kind in ("uniform", "loguniform"):
        return prior.args["lower"], prior.args["upper"]
    if prior.kind == "custom":  # no quantiles, mean ± a few sd
        mean, sd = prior.mean(), prior.sd()
        return mean - _CUSTOM_SDS * sd, mean + _CUSTOM_SDS * sd
    tail = 0.5 * (1.0 - coverage)
    return prior.quantile(tail), prior.quantile(1.0 - tail)


def prior_box(
    physics: PhysicsModel,
    *,
    coverage: float = 0.99,
    bounds: Mapping[str, tuple[float, float]] | None = None,
) -> dict[str, tuple[float, float]]:
    """The search box of every physics parameter, from its prior.

    Uniform priors give their support; Normal, LogNormal and HalfNormal priors their
    central ``coverage`` interval (the 0.5 %–99.5 % quantiles by default); custom priors,
    whose quantiles are unknown, ``mean ± 3 sd``.  ``bounds`` overrides any of these.

    Parameters
    ----------
    physics : PhysicsModel
        Model whose parameters (and priors) span the box.
    coverage : float
        Prior probability inside the box of an unbounded prior, in (0, 1).
    bounds : mapping, optional
        Parameter name -> ``(lower, upper)``, replacing the prior's box.

    Returns
    -------
    dict
        Parameter name -> ``(lower, upper)``, finite with ``lower < upper``.

    Raises
    ------
    ValueError
        A box that is not finite or empty, naming the parameter; an unknown name in
        ``bounds``; ``coverage`` outside (0, 1).

    Examples
    --------
    >>> from kohpymc import Normal, PhysicsModel, Uniform
    >>> physics = PhysicsModel(lambda x, p: p["a"] * x["t"],
    ...                        {"a": Uniform(0, 5), "b": Normal(0, 1)}, inputs=["t"])
    >>> {k: tuple(round(v, 3) for v in b) for k, b in prior_box(physics).items()}
    {'a': (0.0, 5.0), 'b': (-2.576, 2.576)}
    """
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"coverage must be in (0, 1), got {coverage}")
    bounds = dict(bounds or {})
    unknown = sorted(set(bounds) - set(physics.parameters))
    if unknown:
        raise ValueError(
            f"bounds name unknown parameter(s) {unknown}; the physics model "
            f"{physics.name!r} has {list(physics.parameters)}"
        )
    box = {}
    for name, prior in physics.parameters.items():
        lo, hi = bounds[name] if name in bounds else _quantile_box(prior, coverage)
        lo, hi = float(lo), float(hi)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(
                f"parameter {name!r}: no finite search box (got [{lo}, {hi}] from "
                f"{'bounds' if name in bounds else repr(prior)}); pass bounds={{{name!r}: "
                "(lower, upper)}"
            )
        box[name] = (lo, hi)
    return box


def _starts(n_params: int, starts: int, seed: int, margin: float) -> np.ndarray:
    """The first ``starts`` points of a scrambled Sobol sequence in the unit cube."""
    from scipy.stats import qmc

    n_sobol = 1 << max(0, int(np.ceil(np.log2(starts))))
    points = qmc.Sobol(n_params, seed=seed).random(n_sobol)[:starts]
    return np.clip(points, margin, 1.0 - margin)


def multistart_least_squares(
    physics: PhysicsModel,
    data: CalibrationData,
    *,
    starts: int = 8,
    seed: int = 0,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
    data_transform: Callable[[np.ndarray], np.ndarray] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    coverage: float = 0.99,
    margin: float = 1e-3,
    screen_tol: float = 1e-4,
) -> MultistartResult:
    r"""Least-squares fit of the physics model from several space-filling starts.

    Minimises ``½ Σ ((G(x_i; θ) - y_i) / σ)²`` over the box of :func:`prior_box`
    shrunk by ``margin`` × its width on each side (so the fit lies strictly inside the
    prior support and can be passed as ``initvals``), from the first ``starts`` points
    of a scrambled Sobol design, each parameter scaled to ``[0, 1]`` over its box.
    Without ``transform`` every start is fitted to SciPy's default tolerances and the
    best is returned.  With ``transform`` every start is fitted on
    ``transform(G) - data_transform(y)`` to tolerances ``screen_tol`` (it only has to
    land in the right basin), then the best of these is refined on the raw residuals.
    Where the model raises or returns NaN/inf, the residuals are set to 1e100.

    Parameters
    ----------
    physics : PhysicsModel
        The model; evaluated with :meth:`~kohpymc.PhysicsModel.evaluate`.
    data : CalibrationData
        Data with (at least) the physics model's inputs.  ``σ`` is its known noise sd,
        else the sd of ``y`` (1 if that is 0).
    starts : int
        Number of starting points (>= 1).
    seed : int
        Seed of the Sobol scrambling.
    transform : callable, optional
        Output transform of a first, screening fit, e.g. ``lambda g: np.log(np.maximum(g,
        1e-300))`` for outputs spanning orders of magnitude.
    data_transform : callable, optional
        The transform applied to ``y`` (default ``transform``); e.g. a log with a floor
        at the noise level for noisy data near zero.
    bounds : mapping, optional
        Parameter name -> ``(lower, upper)`` overriding the prior box.
    coverage : float
        Prior mass of the box of an unbounded prior (see :func:`prior_box`).
    margin : float
        Fraction of each box width kept clear of its ends, in [0, 0.5).
    screen_tol : float
        ``ftol`` and ``xtol`` of the transformed (screening) fits.

    Returns
    -------
    MultistartResult
        ``params`` (the best fit, a dict to pass as ``initvals``), its ``cost`` and
        every start's local fit and cost.

    Raises
    ------
    ValueError
        ``starts < 1``, ``margin`` outside [0, 0.5), or a parameter without a finite
        box (named in the message).
    PhysicsModelError
        The model failed or returned non-finite values from every start.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import CalibrationData, PhysicsModel, Uniform
    >>> def decay(x, p):
    ...     return p["A"] * np.exp(-x["t"] / p["tau"])
    >>> physics = PhysicsModel(decay, {"A": Uniform(10, 1e4), "tau": Uniform(1e-4, 1e-2)},
    ...                        inputs=["t"])
    >>> t = np.linspace(0.0, 5e-3, 30)
    >>> data = CalibrationData({"t": t}, decay({"t": t}, {"A": 1e3, "tau": 1e-3}), noise_sd=1.0)
    >>> fit = multistart_least_squares(physics, data, starts=4)
    >>> round(fit.params["A"], 3), round(fit.params["tau"], 8)
    (1000.0, 0.001)
    """
    from scipy.optimize import least_squares

    if starts < 1:
        raise ValueError(f"starts must be >= 1, got {starts}")
    if not 0.0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin}")
    box = prior_box(physics, coverage=coverage, bounds=bounds)
    names = tuple(box)
    lower = np.array([box[k][0] for k in names])
    width = np.array([box[k][1] for k in names]) - lower
    inputs = {k: data.inputs[k] for k in physics.inputs}
    y = np.asarray(data.y, dtype=float)
    sd = float(data.noise_sd) if data.noise_sd is not None else float(np.std(y)) or 1.0

    def model(u: np.ndarray) -> np.ndarray:
        try:
            return physics.evaluate(inputs, lower + width * u, check_finite=False)
        except PhysicsModelError:
            return np.full(y.size, np.nan)

    def guarded(r: np.ndarray) -> np.ndarray:
        return np.where(np.isfinite(r), r, _BAD)

    def residual(u: np.ndarray) -> np.ndarray:
        return guarded((model(u) - y) / sd)

    cube = (np.full(len(names), margin), np.full(len(names), 1.0 - margin))
    u0 = _starts(len(names), starts, seed, margin)
    if transform is None:
        fits = [least_squares(residual, u, bounds=cube) for u in u0]
    else:
        target = (data_transform or transform)(y)

        def screen(u: np.ndarray) -> np.ndarray:
            return guarded(transform(model(u)) - target)

        fits = [least_squares(screen, u, bounds=cube, ftol=screen_tol, xtol=screen_tol) for u in u0]
    best = min(fits, key=lambda r: r.cost)
    final = best if transform is None else least_squares(residual, best.x, bounds=cube)
    if not final.cost < 0.5 * _BAD**2:
        raise PhysicsModelError(
            f"physics model {physics.name!r} failed or returned non-finite values from "
            f"all {starts} start(s)"
        )
    theta = lower + width * final.x
    return MultistartResult(
        params={k: float(v) for k, v in zip(names, theta, strict=True)},
        cost=float(final.cost),
        names=names,
        starts=lower + width * u0,
        fits=lower + width * np.array([r.x for r in fits]),
        start_costs=np.array([r.cost for r in fits]),
        lower=lower + margin * width,
        upper=lower + (1.0 - margin) * width,
    )
