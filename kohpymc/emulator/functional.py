r"""Functional outputs: a principal-component basis with independent GPs on the weights.

A simulator that computes a whole curve per run (a current against time, a profile
against depth) is emulated as in GPMSA / SEPIA (Higdon et al. 2008, *J. Am. Stat.
Assoc.* 103:570): every run gives its output on one fixed **grid** of the functional
input(s); the curves are centred and scaled, their principal components (an SVD) give a
basis, and each of the ``K`` kept component weights is emulated by its own ARD GP over
the **scalar inputs** (the physics inputs not on the grid) and the parameters θ.

Notation: ``g_r`` the output curve of run ``r`` on the ``P`` grid points (``ln`` of the
output with ``log_output=True``), ``μ`` the mean curve, ``s`` the overall sd,
``Y = (G - μ) / s = U S Vᵀ``.  The basis ``Φ = V_K S_K / √n`` (``P × K``) and weights
``W = √n U_K`` (unit variance), so ``Y ≈ W Φᵀ``; ``K`` is the smallest number of
components whose share of ``Σ S²`` reaches ``variance`` (default 0.999).  The part
the basis misses is the truncation error, with variance ``τ_p`` per grid point (the mean
squared residual of the training curves; GPMSA uses one such variance for the whole
curve).  At scalar inputs ``x`` and θ, with GP means ``ŵ_k`` and covariances
``c_k(x, x')`` of the weights (each GP is an :class:`~kohpymc.emulator.gp.Emulator`-style
fit: unit-box columns, Matérn 5/2 or SE kernel, nugget, MAP hyperparameters)::

    E[g(x, p)]        = μ_p + s Σ_k Φ_pk ŵ_k(x, θ)
    Cov[g(x,p), g(x',p')] = s² (Σ_k Φ_pk Φ_p'k c_k(x, x') + τ_p 1[x = x', p = p'])

so the emulator's covariance between the rows of one curve is dense (rank ``K`` plus
the truncation diagonal), and rows at different scalar settings are correlated through
``c_k``.  With ``log_output=True`` the mean and covariance are those of the log-normal
``exp(g)``.  Data rows off the grid: with one functional input the basis, mean and
truncation variance are interpolated linearly between the neighbouring grid points
(outside the grid is an error); with several functional inputs every data row must lie
on the grid (to a relative 1e-9).

:meth:`FunctionalEmulator.physics_model` wraps it as a
:class:`FunctionalEmulatedPhysics`, a :class:`~kohpymc.PhysicsModel` like
:class:`~kohpymc.emulator.gp.EmulatedPhysics`: its mean is a PyTensor expression of θ
(exact gradients) and :meth:`~FunctionalEmulatedPhysics.covariance_tensor` the full
``Σ_η(θ)`` between the calibration rows, which :func:`kohpymc.model.compose_model` adds
to the likelihood covariance of every formulation that accepts it (the others get its
diagonal added to the noise variance).  The rows' input values must be known numbers
when the model is built (they are, in :func:`~kohpymc.model.compose_model`).

``Σ_η`` is the truncation diagonal plus a rank ``K m`` term (``m`` distinct scalar
settings among the rows); when that holds (see
:meth:`FunctionalEmulator.covariance_tensor`) it is built as a
:func:`~kohpymc.gaussian.low_rank_covariance`, and M0–M3, whose own covariance is
diagonal plus the low-rank term of a marginalized mean, evaluate the likelihood by the
Woodbury identity in ``O(n (K m)²)`` instead of factorizing ``n × n``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import pytensor.tensor as pt
from pymc.pytensorf import constant_fold
from pytensor.graph.basic import Constant
from pytensor.graph.traversal import graph_inputs
from scipy import linalg

from kohpymc.emulator.checking import EmulatorCheck, fit_problems
from kohpymc.emulator.design import log_scaled
from kohpymc.emulator.gp import (
    KERNELS,
    EmulatedPhysics,
    EmulatorWarning,
    GPHyperparameters,
    SharedTrainingData,
    _fit_hyperparameters,
    _kernel_numpy,
    shared_array,
)
from kohpymc.emulator.quadratic import kernel_quadratic, kernel_values
from kohpymc.emulator.runs import (
    _cache_folder,
    _read_cache,
    _simulate,
    _write_record,
    point_key,
    simulator_identity,
)
from kohpymc.execution import run_tasks
from kohpymc.gaussian import low_rank_covariance, low_rank_parts
from kohpymc.physics import PhysicsModel
from kohpymc.warning_filters import warn_user

__all__ = [
    "FunctionalEmulatedPhysics",
    "FunctionalEmulator",
    "FunctionalRuns",
    "at_settings",
    "distinct_rows",
    "merged_curves",
    "posterior_curve_design",
    "run_curves",
]


@dataclass
class FunctionalRuns:
    """Simulator curves: one row of scalar inputs and θ per run, its output on a grid.

    Attributes
    ----------
    design : pandas.DataFrame
        Successful runs: one column per scalar input (physics inputs not on the grid),
        then per parameter.
    grid : pandas.DataFrame
        The functional input(s), one row per grid point (``P`` rows).
    curves : numpy.ndarray
        ``(n_runs, P)`` outputs.
    inputs, parameters : tuple of str
        The scalar inputs and the parameters (the columns of ``design``).
    failed : pandas.DataFrame
        Design rows of which at least one grid point failed.
    simulated, cached : int
        Curves run in this call / read from the cache.
    seconds : float
        Wall time of the simulator tasks of this call (summed over tasks).

    Examples
    --------
    See :func:`run_curves`.
    """

    design: pd.DataFrame
    grid: pd.DataFrame
    curves: np.ndarray
    inputs: tuple[str, ...]
    parameters: tuple[str, ...]
    failed: pd.DataFrame
    simulated: int = 0
    cached: int = 0
    seconds: float = 0.0

    @property
    def n_runs(self) -> int:
        """Number of successful curves."""
        return len(self.curves)

    @property
    def X(self) -> np.ndarray:
        """``(n_runs, d_s + p)``: scalar-input columns, then parameter columns."""
        return self.design[list(self.inputs + self.parameters)].to_numpy(float)

    def subset(self, rows: Any) -> FunctionalRuns:
        """The runs at ``rows`` (a boolean mask or integer positions)."""
        idx = np.arange(self.n_runs)[rows]
        return FunctionalRuns(
            self.design.iloc[idx].reset_index(drop=True),
            self.grid,
            self.curves[idx],
            self.inputs,
            self.parameters,
            self.failed.iloc[:0],
        )


def merged_curves(a: FunctionalRuns, b: FunctionalRuns) -> FunctionalRuns:
    """The curves of ``a`` and ``b`` (on one grid) as one set of runs.

    Examples
    --------
    >>> from kohpymc import PhysicsModel, Uniform
    >>> line = PhysicsModel(lambda x, p: p["a"] * x["t"], {"a": Uniform(0, 1)}, inputs=["t"])
    >>> grid = {"t": [0.0, 1.0]}
    >>> one = run_curves(line, pd.DataFrame({"a": [0.2]}), grid)
    >>> merged_curves(one, run_curves(line, pd.DataFrame({"a": [0.4]}), grid)).curves.tolist()
    [[0.0, 0.2], [0.0, 0.4]]
    """
    if not a.grid.equals(b.grid) or (a.inputs, a.parameters) != (b.inputs, b.parameters):
        raise ValueError("merged_curves: the runs differ in grid, scalar inputs or parameters")
    return FunctionalRuns(
        design=pd.concat([a.design, b.design], ignore_index=True),
        grid=a.grid,
        curves=np.vstack([a.curves, b.curves]),
        inputs=a.inputs,
        parameters=a.parameters,
        failed=pd.concat([a.failed, b.failed], ignore_index=True),
        simulated=a.simulated + b.simulated,
        cached=a.cached + b.cached,
        seconds=a.seconds + b.seconds,
    )


def posterior_curve_design(
    draws: pd.DataFrame,
    data: Any,
    emulator: FunctionalEmulator,
    n_new: int,
    *,
    seed: int = 0,
) -> pd.DataFrame:
    """New curves: posterior draws of θ, each at every scalar setting of the data.

    The curve counterpart of :func:`~kohpymc.emulator.sequential.posterior_design`:
    ``max(1, round(n_new / m))`` draws picked at random (``m`` distinct settings of the
    scalar inputs among the calibration rows, 1 without scalar inputs), each run at
    every setting, a whole curve per run (about ``n_new`` curves).

    Examples
    --------
    >>> from kohpymc import CalibrationData, PhysicsModel, Uniform
    >>> from kohpymc.emulator import space_filling_design
    >>> f = PhysicsModel(lambda x, p: p["a"] * x["t"] + x["s"], {"a": Uniform(0, 1)},
    ...                  inputs=["s", "t"])
    >>> box = {"s": (0, 1), "a": (0, 1)}
    >>> em = FunctionalEmulator(run_curves(f, space_filling_design(box, 6), {"t": [0, 1, 2]}), f)
    >>> data = CalibrationData({"s": [0.0, 0.0, 1.0], "t": [0.5, 1.5, 1.0]}, [0.1, 0.3, 1.2])
    >>> posterior_curve_design(pd.DataFrame({"a": [0.2, 0.3]}), data, em, 4)
    ...                                                       # doctest: +NORMALIZE_WHITESPACE
         s    a
    0  0.0  0.2
    1  1.0  0.2
    2  0.0  0.3
    3  1.0  0.3
    """
    params = list(emulator.runs.parameters)
    scalar = list(emulator.scalar_inputs)
    missing = [k for k in params if k not in draws.columns]
    if missing:
        raise KeyError(f"posterior_curve_design: the draws lack parameter(s) {missing}")
    settings = distinct_rows(scalar, data)
    k = min(len(draws), max(1, int(round(n_new / len(settings)))))
    rng = np.random.default_rng(seed)
    picked = draws[params].iloc[rng.choice(len(draws), size=k, replace=False)]
    return at_settings(picked, settings, scalar, params)


def distinct_rows(columns: Sequence[str], *data: Any) -> np.ndarray:
    """The distinct rows of the input ``columns`` over the data sets, sorted.

    No columns: one empty row (a curve design without scalar inputs has one setting).

    Examples
    --------
    >>> from kohpymc import CalibrationData
    >>> a = CalibrationData({"s": [1.0, 0.0, 1.0], "t": [0.0, 1.0, 2.0]}, [0.0, 0.0, 0.0])
    >>> b = CalibrationData({"s": [2.0], "t": [1.0]}, [0.0])
    >>> distinct_rows(["s"], a, b).ravel().tolist(), distinct_rows([], a).shape
    ([0.0, 1.0, 2.0], (1, 0))
    """
    if not columns:
        return np.empty((1, 0))
    return np.unique(np.vstack([d.matrix(tuple(columns)) for d in data]), axis=0)


def at_settings(
    thetas: pd.DataFrame, settings: np.ndarray, scalar: Sequence[str], parameters: Sequence[str]
) -> pd.DataFrame:
    """A curve design: every θ (a row of ``thetas``) at every setting of the scalar inputs.

    Examples
    --------
    >>> at_settings(pd.DataFrame({"a": [0.2, 0.3]}), np.array([[0.0], [1.0]]), ["s"], ["a"])
    ...                                                       # doctest: +NORMALIZE_WHITESPACE
         s    a
    0  0.0  0.2
    1  1.0  0.2
    2  0.0  0.3
    3  1.0  0.3
    """
    m = len(settings)
    values = thetas[list(parameters)].to_numpy(float)
    rows = [np.column_stack([settings, np.tile(theta, (m, 1))]) for theta in values]
    return pd.DataFrame(np.vstack(rows), columns=[*scalar, *parameters])


def run_curves(
    physics: PhysicsModel,
    design: pd.DataFrame,
    grid: pd.DataFrame | Mapping[str, Any],
    *,
    cache: str | Path | None = None,
    simulator_label: str | None = None,
    workers: int = 1,
    scheduler: Any = None,
    progress: Any = None,
) -> FunctionalRuns:
    """Run the simulator on the whole grid at every row of ``design``.

    Every design row (scalar inputs and θ) is one task, one simulator call over the
    whole grid, run by :func:`kohpymc.run_tasks` (``workers``, ``scheduler`` and
    ``progress`` are passed on).  With ``cache`` a folder, every finished curve is
    written there as one JSON file named by a hash of (design row, simulator identity,
    grid), and a rerun only runs the rows not there yet.  A row whose call failed or
    gave a non-finite value goes to ``failed`` (with its error).

    Parameters
    ----------
    physics : PhysicsModel
        The simulator; its inputs are the grid's columns plus the scalar inputs.
    design : pandas.DataFrame
        One column per scalar input and per parameter.
    grid : DataFrame or mapping
        The functional input(s): one column per functional input, one row per point.

    Returns
    -------
    FunctionalRuns

    Examples
    --------
    >>> import pytensor.tensor as pt
    >>> from kohpymc import PhysicsModel, Uniform
    >>> decay = PhysicsModel(lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
    ...                      {"a": Uniform(1, 2), "k": Uniform(0.5, 1)}, inputs=["t"])
    >>> runs = run_curves(decay, pd.DataFrame({"a": [1.0, 2.0], "k": [0.5, 1.0]}),
    ...                   {"t": [0.0, 1.0, 2.0]})
    >>> runs.curves.shape, float(runs.curves[1, 0])
    ((2, 3), 2.0)
    """
    grid = pd.DataFrame(grid).reset_index(drop=True).astype(float)
    scalar, params = _curve_columns(physics, grid)
    columns = list(scalar + params)
    design, values = _curve_design(design, columns)
    simulator = _grid_simulator(physics, simulator_label, grid)
    folder = _cache_folder(cache)
    keys = [point_key(dict(zip(columns, row.tolist(), strict=True)), simulator) for row in values]
    curves, tasks, cached = _plan_curves(
        physics, values, keys, columns, grid, scalar, params, folder
    )
    done, errors, seconds = _run_curve_tasks(
        tasks, scalar, simulator, folder, workers, scheduler, progress
    )
    for r, key in enumerate(keys):
        if key in done:
            curves[r] = done[key]
    ok = np.all(np.isfinite(curves), axis=1)
    failed = design[~ok].reset_index(drop=True)
    failed["error"] = [errors.get(keys[r], "non-finite output") for r in np.flatnonzero(~ok)]
    return FunctionalRuns(
        design=design[ok].reset_index(drop=True),
        grid=grid,
        curves=curves[ok],
        inputs=scalar,
        parameters=params,
        failed=failed,
        simulated=len(tasks),
        cached=cached,
        seconds=seconds,
    )


def _curve_columns(
    physics: PhysicsModel, grid: pd.DataFrame
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The scalar inputs (those not on the grid) and the parameters; checks the grid's."""
    functional = tuple(grid.columns)
    unknown = [k for k in functional if k not in physics.inputs]
    if unknown:
        raise KeyError(f"run_curves: grid column(s) {unknown} are not inputs of {physics.name!r}")
    scalar = tuple(k for k in physics.inputs if k not in functional)
    return scalar, tuple(physics.parameters)


def _curve_design(design: pd.DataFrame, columns: list[str]) -> tuple[pd.DataFrame, np.ndarray]:
    """The design's ``columns`` as floats (frame and array); missing columns or NaN raise."""
    missing = [k for k in columns if k not in design.columns]
    if missing:
        raise KeyError(f"run_curves: the design lacks column(s) {missing}")
    design = design[columns].reset_index(drop=True).astype(float)
    values = design.to_numpy(float)
    if not np.all(np.isfinite(values)):
        raise ValueError("run_curves: the design contains NaN/inf")
    return design, values


def _grid_simulator(physics: PhysicsModel, simulator_label: str | None, grid: pd.DataFrame) -> str:
    """The simulator identity of the cache keys, extended by a hash of the grid."""
    functional, grid_values = tuple(grid.columns), grid.to_numpy(float)
    digest = hashlib.sha256(
        json.dumps(
            [list(functional), [[repr(v) for v in r] for r in grid_values.tolist()]]
        ).encode()
    ).hexdigest()[:16]
    return f"{simulator_identity(physics, simulator_label)}:grid:{digest}"


def _plan_curves(
    physics: PhysicsModel,
    values: np.ndarray,
    keys: list[str],
    columns: list[str],
    grid: pd.DataFrame,
    scalar: tuple[str, ...],
    params: tuple[str, ...],
    folder: Path | None,
) -> tuple[np.ndarray, dict[str, Any], int]:
    """Curves read from the cache (NaN rows elsewhere), one task per other distinct row.

    Returns the ``(n, P)`` curves, the tasks (key -> (physics, inputs, θ)) and the
    number of curves read from the cache.
    """
    n, P = len(values), len(grid)
    grid_values = grid.to_numpy(float)
    functional = tuple(grid.columns)
    curves = np.full((n, P), np.nan)
    tasks: dict[str, Any] = {}
    cached = 0
    for r, key in enumerate(keys):
        hit = None if folder is None else _read_cache(folder / f"{key}.json")
        if hit is not None and hit.get("curve") is not None:
            curves[r] = hit["curve"]
            cached += 1
            continue
        if key in tasks:
            continue
        row = dict(zip(columns, values[r].tolist(), strict=True))
        inputs = {k: grid_values[:, j].tolist() for j, k in enumerate(functional)}
        inputs.update({k: [row[k]] * P for k in scalar})
        tasks[key] = (physics, inputs, {k: row[k] for k in params})
    return curves, tasks, cached


def _run_curve_tasks(
    tasks: dict[str, Any],
    scalar: tuple[str, ...],
    simulator: str,
    folder: Path | None,
    workers: int,
    scheduler: Any,
    progress: Any,
) -> tuple[dict[str, Any], dict[str, str], float]:
    """Run the tasks (writing each curve to the cache): curves, errors by key, seconds."""
    done: dict[str, Any] = {}
    errors: dict[str, str] = {}
    seconds = 0.0
    for outcome in run_tasks(
        _simulate, tasks, workers=workers, scheduler=scheduler, progress=progress
    ):
        seconds += outcome.seconds
        if outcome.error is None:
            done[outcome.key] = outcome.value
        else:
            errors[outcome.key] = str(outcome.error)
        if folder is not None:
            record = {
                "point": tasks[outcome.key][2] | {k: tasks[outcome.key][1][k][0] for k in scalar},
                "curve": done.get(outcome.key),
                "error": errors.get(outcome.key),
                "simulator": simulator,
            }
            _write_record(folder / f"{outcome.key}.json", record)
    return done, errors, seconds


class _WeightGP:
    """One GP on one component weight (fixed hyperparameters after the fit)."""

    def __init__(self, kernel: str, U: np.ndarray, z: np.ndarray, hyper: GPHyperparameters):
        self.kernel, self.U, self.z, self.hyper = kernel, U, z, hyper
        R, _ = _kernel_numpy(kernel, U, U, hyper.lengthscales, hyper.amplitude)
        K = R + (hyper.nugget + 1e-10) * np.eye(len(z))
        chol = linalg.cholesky(K, lower=True)
        self.alpha = linalg.cho_solve((chol, True), z)
        self.chol_inv = linalg.solve_triangular(chol, np.eye(len(z)), lower=True)

    def predict(self, Us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(m,)`` and covariance ``(m, m)`` (latent plus nugget) at rows ``Us``."""
        h = self.hyper
        Ks, _ = _kernel_numpy(self.kernel, Us, self.U, h.lengthscales, h.amplitude)
        prior, _ = _kernel_numpy(self.kernel, Us, Us, h.lengthscales, h.amplitude)
        V = self.chol_inv @ Ks.T
        cov = prior - V.T @ V + h.nugget * np.eye(len(Us))
        if len(Us) == 1:  # as the tensors: a variance lost to rounding is the nugget
            cov = np.maximum(cov, h.nugget)
        return Ks @ self.alpha, cov

    def without(self, drop: np.ndarray) -> _WeightGP:
        """The GP conditioned on the training rows not in ``drop`` (same hyperparameters)."""
        keep = ~np.asarray(drop, dtype=bool)
        return _WeightGP(self.kernel, self.U[keep], self.z[keep], self.hyper)

    def predict_each(self, Us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance ``(m,)`` at every row of ``Us`` alone (``predict`` row by row)."""
        h = self.hyper
        Ks, _ = _kernel_numpy(self.kernel, Us, self.U, h.lengthscales, h.amplitude)
        V = self.chol_inv @ Ks.T
        var = h.amplitude + h.nugget - np.sum(V**2, axis=0)
        return Ks @ self.alpha, np.maximum(var, h.nugget)


def _check_emulator_arguments(
    runs: FunctionalRuns, physics: PhysicsModel, kernel: str, variance: float
) -> tuple[str, ...]:
    """Check the arguments of :class:`FunctionalEmulator`; return the functional inputs."""
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {list(KERNELS)}, got {kernel!r}")
    if not 0.0 < variance <= 1.0:
        raise ValueError(f"variance must be in (0, 1], got {variance}")
    functional = tuple(runs.grid.columns)
    if tuple(physics.parameters) != tuple(runs.parameters) or set(physics.inputs) != set(
        runs.inputs + functional
    ):
        raise ValueError(
            f"FunctionalEmulator: the runs have scalar inputs {list(runs.inputs)}, grid "
            f"{list(functional)} and parameters {list(runs.parameters)}; the physics "
            f"model {physics.name!r} has inputs {list(physics.inputs)} and parameters "
            f"{list(physics.parameters)}"
        )
    if runs.n_runs < 3:
        raise ValueError(f"FunctionalEmulator needs at least 3 curves, got {runs.n_runs}")
    return functional


def _box_bounds(
    columns: tuple[str, ...], X: np.ndarray, box: Mapping[str, tuple[float, float]] | None
) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bound of every column: ``box``'s where given, else the runs' range."""
    box = dict(box or {})
    lo = np.array([box[k][0] if k in box else X[:, j].min() for j, k in enumerate(columns)])
    hi = np.array([box[k][1] if k in box else X[:, j].max() for j, k in enumerate(columns)])
    return lo, hi


def _check_rotation(rotation: tuple[Any, Any], p: int) -> tuple[np.ndarray, np.ndarray]:
    """``(center, matrix)`` of a θ rotation as float arrays of shapes ``(p,)``, ``(p, p)``."""
    center, matrix = (np.asarray(a, dtype=float) for a in rotation)
    if center.shape != (p,) or matrix.shape != (p, p):
        raise ValueError(
            f"rotation must be (center ({p},), matrix ({p}, {p})), got "
            f"{center.shape} and {matrix.shape}"
        )
    return center, matrix


@dataclass(frozen=True)
class _Rows:
    """Where calibration rows sit: scalar settings and interpolation onto the grid."""

    settings: np.ndarray  # (m, d_s) distinct scalar-input values (raw)
    setting_index: np.ndarray  # (n,) row -> setting
    interp: np.ndarray  # (n, P) row -> grid weights


class FunctionalEmulator(SharedTrainingData):
    r"""A principal-component emulator of a simulator's curves (GPMSA / SEPIA style).

    Parameters
    ----------
    runs : FunctionalRuns
        Training curves (:func:`run_curves`).
    physics : PhysicsModel
        The simulator: its priors become those of :meth:`physics_model`.
    variance : float
        Keep the fewest components whose share of the curves' variance reaches this
        (default 0.999).
    n_components : int, optional
        Keep exactly this many components instead.
    log_output : bool
        Build the basis from ln output (every output must be positive); predictions
        are log-normal means and covariances in output units.
    kernel : {"matern52", "se"}
        Kernel of the weight GPs (see :class:`~kohpymc.emulator.gp.Emulator`).
    box : mapping, optional
        Column -> ``(lower, upper)`` of the unit box of the scalar inputs and θ (default:
        the runs' range); columns spanning two decades or more are log-scaled.
    log_parameters : sequence of str
        Columns to log-scale in any case (positive parameters whose posterior is a
        power law, e.g. ``B ∝ √m* Φ_B^{3/2}``, is a straight line in logs).
    rotation : (center, matrix), optional
        GP coordinates of θ ``u = M (h(θ) - c)`` (``h`` the log-scaling above), e.g.
        whitened by a Laplace covariance at a first fit (``M = Λ^{-1/2} Vᵀ``), so that
        a design in ``u`` covers a thin, tilted posterior and the ARD length scales act
        along its principal axes; the unit box is then the runs' range of ``u``.
    restarts, seed :
        Starts of the hyperparameter search of each weight GP, and their seed.

    Attributes
    ----------
    basis : numpy.ndarray
        ``Φ``, ``(P, K)``.
    weights : numpy.ndarray
        ``W``, ``(n_runs, K)``, the training weights (unit variance).
    mean_curve, curve_scale : numpy.ndarray, float
        ``μ`` and ``s``.
    truncation_variance : numpy.ndarray
        ``τ``, ``(P,)``, in standardised units.
    explained : float
        Share of the variance the kept components carry.
    hypers : list of GPHyperparameters

    Examples
    --------
    >>> import pytensor.tensor as pt
    >>> from kohpymc import PhysicsModel, Uniform
    >>> from kohpymc.emulator import space_filling_design
    >>> decay = PhysicsModel(lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
    ...                      {"a": Uniform(1, 2), "k": Uniform(0.5, 1)}, inputs=["t"])
    >>> design = space_filling_design({"a": (1, 2), "k": (0.5, 1)}, 20, seed=1)
    >>> em = FunctionalEmulator(run_curves(decay, design, {"t": np.linspace(0, 3, 16)}), decay)
    >>> em.n_components <= 4
    True
    >>> mean, var = em.predict({"t": [0.5, 1.1]}, {"a": 1.5, "k": 0.7})
    >>> bool(np.allclose(mean, 1.5 * np.exp(-0.7 * np.array([0.5, 1.1])), atol=1e-2))
    True
    >>> mean, sd = em.predict_curves(pd.DataFrame({"a": [1.5], "k": [0.7]}))
    >>> bool(np.allclose(mean[0], 1.5 * np.exp(-0.7 * np.linspace(0, 3, 16)), atol=1e-2))
    True
    """

    def __init__(
        self,
        runs: FunctionalRuns,
        physics: PhysicsModel,
        *,
        variance: float = 0.999,
        n_components: int | None = None,
        log_output: bool = False,
        kernel: Literal["se", "matern52"] = "matern52",
        box: Mapping[str, tuple[float, float]] | None = None,
        log_parameters: Sequence[str] = (),
        rotation: tuple[Any, Any] | None = None,
        restarts: int = 3,
        seed: int = 0,
    ) -> None:
        functional = _check_emulator_arguments(runs, physics, kernel, variance)
        #: the fit's settings, kept by :meth:`refitted`
        self.options: dict[str, Any] = {
            "variance": variance, "n_components": n_components, "log_output": log_output,
            "kernel": kernel, "box": box, "log_parameters": tuple(log_parameters),
            "rotation": rotation, "restarts": restarts,
        }  # fmt: skip
        self.physics = physics
        self.runs = runs
        self.kernel = kernel
        self.functional = functional
        self.scalar_inputs = tuple(runs.inputs)
        self.columns = tuple(runs.inputs + runs.parameters)
        self.grid = runs.grid[list(functional)].to_numpy(float)
        self._set_unit_box(runs.X, box, log_parameters, rotation)
        Y = self._standardized_curves(np.asarray(runs.curves, dtype=float), log_output)
        self._set_basis(Y, variance, n_components)
        self._fit_weight_gps(restarts, seed)

    def refitted(self, new: FunctionalRuns, *, seed: int = 0) -> FunctionalEmulator:
        """The emulator fitted again to its curves and ``new`` ones, with its settings.

        The basis is recomputed from all curves (``K`` by ``variance``, unless
        ``n_components`` was given); with ``log_output`` and a new curve ``<= 0``
        somewhere, the refit is on the linear scale.

        Examples
        --------
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> decay = PhysicsModel(lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
        ...                      {"a": Uniform(1, 2), "k": Uniform(0.5, 1)}, inputs=["t"])
        >>> box, grid = {"a": (1, 2), "k": (0.5, 1)}, {"t": np.linspace(0, 3, 16)}
        >>> em = FunctionalEmulator(run_curves(decay, space_filling_design(box, 8), grid), decay)
        >>> more = run_curves(decay, pd.DataFrame({"a": [1.5], "k": [0.7]}), grid)
        >>> em.refitted(more).n_runs
        9
        """
        runs = merged_curves(self.runs, new)
        options = dict(self.options)
        options["log_output"] = bool(options["log_output"]) and bool(np.all(runs.curves > 0))
        return FunctionalEmulator(runs, self.physics, seed=seed, **options)

    def _set_unit_box(
        self,
        X: np.ndarray,
        box: Mapping[str, tuple[float, float]] | None,
        log_parameters: Sequence[str],
        rotation: tuple[Any, Any] | None,
    ) -> None:
        """Set the log-scaled columns, θ rotation and unit box, and the runs' coordinates ``U``."""
        lo, hi = _box_bounds(self.columns, X, box)
        self.log_columns = log_scaled(lo, hi) | np.isin(self.columns, list(log_parameters))
        ds = len(self.scalar_inputs)
        self.rotation = None
        if rotation is not None:
            self.rotation = _check_rotation(rotation, len(self.runs.parameters))
            H = self._coordinates(X)  # rotated: the unit box is the runs' range there
            lo[ds:], hi[ds:] = H[:, ds:].min(axis=0), H[:, ds:].max(axis=0)
            lo[:ds], hi[:ds] = self._transform(lo)[:ds], self._transform(hi)[:ds]
        else:
            lo, hi = self._transform(lo), self._transform(hi)
        self.lower = lo.astype(float)
        self.width = np.where(hi > lo, hi - lo, 1.0).astype(float)
        self.U = (self._coordinates(X) - self.lower) / self.width

    def _standardized_curves(self, curves: np.ndarray, log_output: bool) -> np.ndarray:
        """Set ``μ`` and ``s`` of the (log) curves and return ``Y = (G - μ) / s``."""
        self.log_output = bool(log_output)
        if self.log_output and not np.all(curves > 0):
            raise ValueError(
                f"FunctionalEmulator(log_output=True): {int(np.sum(curves <= 0))} output(s) "
                f"of {self.physics.name!r} are <= 0"
            )
        G = np.log(curves) if self.log_output else curves
        self.mean_curve = G.mean(axis=0)
        sd = float(np.std(G - self.mean_curve))
        self.curve_scale = sd if sd > 0 else 1.0
        return (G - self.mean_curve) / self.curve_scale

    def _set_basis(self, Y: np.ndarray, variance: float, n_components: int | None) -> None:
        """Set the kept principal components ``Φ``, weights ``W`` and truncation variance."""
        n = len(Y)
        u, svals, vt = np.linalg.svd(Y, full_matrices=False)
        share = np.cumsum(svals**2) / max(np.sum(svals**2), 1e-300)
        if n_components is None:
            K = int(np.searchsorted(share, variance - 1e-12) + 1)
        else:
            K = int(n_components)
        K = max(1, min(K, len(svals)))
        self.explained = float(share[K - 1])
        self.singular_values = svals
        self.basis = vt[:K].T * svals[:K] / np.sqrt(n)
        self.weights = u[:, :K] * np.sqrt(n)
        residual = Y - self.weights @ self.basis.T
        self.truncation_variance = np.mean(residual**2, axis=0)

    def _fit_weight_gps(self, restarts: int, seed: int) -> None:
        """Fit one GP per component weight (hyperparameters by MAP, seed ``seed + k``)."""
        self.hypers = [
            _fit_hyperparameters(self.kernel, self.U, self.weights[:, k], restarts, seed + k)
            for k in range(self.n_components)
        ]
        self._gps = [
            _WeightGP(self.kernel, self.U, self.weights[:, k], h) for k, h in enumerate(self.hypers)
        ]

    @property
    def n_components(self) -> int:
        """``K``, the number of principal components kept."""
        return self.basis.shape[1]

    @property
    def n_runs(self) -> int:
        """Number of training curves."""
        return len(self.weights)

    # ------------------------------------------------------------------- numpy
    def _transform(self, values: np.ndarray) -> np.ndarray:
        values = np.asarray(values, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.log_columns, np.log(np.abs(values)), values)

    def _coordinates(self, X: np.ndarray) -> np.ndarray:
        """GP coordinates of rows (scalar inputs, θ) before the unit-box scaling."""
        H = np.atleast_2d(self._transform(X)).copy()
        if self.rotation is not None:
            ds = len(self.scalar_inputs)
            center, matrix = self.rotation
            H[:, ds:] = (H[:, ds:] - center) @ matrix.T
        return H

    def _locate(self, X: np.ndarray) -> _Rows:
        """Settings, grid interpolation and the same-point mask of rows ``X``."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        order = list(self.physics.inputs)
        f_idx = [order.index(k) for k in self.functional]
        s_idx = [order.index(k) for k in self.scalar_inputs]
        F, S = X[:, f_idx], X[:, s_idx]
        n, P = len(X), len(self.grid)
        interp = np.zeros((n, P))
        scale = np.maximum(np.abs(self.grid).max(axis=0), 1.0)
        if len(self.functional) == 1:
            g = self.grid[:, 0]
            order_g = np.argsort(g)
            gs = g[order_g]
            f = F[:, 0]
            tol = 1e-9 * scale[0]
            outside = (f < gs[0] - tol) | (f > gs[-1] + tol)
            if np.any(outside):
                bad = f[outside][0]
                raise ValueError(
                    f"FunctionalEmulator: {self.functional[0]} = {bad:g} is outside the "
                    f"emulator's grid [{gs[0]:g}, {gs[-1]:g}]"
                )
            pos = np.clip(np.searchsorted(gs, f, side="right") - 1, 0, max(P - 2, 0))
            if P == 1:
                interp[:, order_g[0]] = 1.0
            else:
                a = np.clip((f - gs[pos]) / (gs[pos + 1] - gs[pos]), 0.0, 1.0)
                rows = np.arange(n)
                interp[rows, order_g[pos]] += 1.0 - a
                interp[rows, order_g[pos + 1]] += a
        else:
            diff = np.abs(F[:, None, :] - self.grid[None, :, :]) / scale
            hit = np.all(diff <= 1e-9, axis=-1)
            missing = ~hit.any(axis=1)
            if np.any(missing):
                bad = dict(zip(self.functional, F[np.argmax(missing)].tolist(), strict=True))
                raise ValueError(
                    f"FunctionalEmulator: {int(missing.sum())} row(s) are not on the grid of "
                    f"{list(self.functional)} (first: {bad}); with several functional inputs "
                    "the data must lie on the grid"
                )
            interp[np.arange(n), np.argmax(hit, axis=1)] = 1.0
        if S.shape[1]:
            settings, index = np.unique(S, axis=0, return_inverse=True)
        else:
            settings, index = np.zeros((1, 0)), np.zeros(n, dtype=int)
        return _Rows(settings, np.asarray(index).reshape(-1), interp)

    def _unit_settings(self, settings: np.ndarray) -> np.ndarray:
        ds = len(self.scalar_inputs)
        if ds == 0:
            return np.zeros((len(settings), 0))
        return (self._transform_cols(settings, slice(0, ds)) - self.lower[:ds]) / self.width[:ds]

    def _transform_cols(self, values: np.ndarray, cols: slice) -> np.ndarray:
        values = np.asarray(values, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.log_columns[cols], np.log(np.abs(values)), values)

    def _latent_numpy(
        self, X: np.ndarray, theta: np.ndarray, without: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Latent (standardised-space transformed back) mean ``(n,)`` and cov ``(n, n)``.

        ``without``: a mask of the runs the weight GPs leave out (basis kept).
        """
        loc = self._locate(X)
        ds = len(self.scalar_inputs)
        coords = self._coordinates(np.r_[np.zeros(ds), np.asarray(theta, dtype=float)][None, :])
        t_unit = (coords[0, ds:] - self.lower[ds:]) / self.width[ds:]
        Us = np.column_stack(
            [self._unit_settings(loc.settings), np.tile(t_unit, (len(loc.settings), 1))]
        )
        B = loc.interp @ self.basis  # (n, K)
        mean = loc.interp @ self.mean_curve
        idx = loc.setting_index
        w_mean = np.zeros(len(X))
        cov_w = np.zeros((len(X), len(X)))
        gps = self._gps
        if without is not None and np.any(without):
            gps = [gp.without(without) for gp in gps]
        for k, gp in enumerate(gps):
            m, c = gp.predict(Us)
            w_mean += B[:, k] * m[idx]
            cov_w += np.outer(B[:, k], B[:, k]) * c[np.ix_(idx, idx)]
        trunc = self._truncation(loc)
        s = self.curve_scale
        return mean + s * w_mean, s**2 * (cov_w + trunc)

    def _truncation(self, loc: _Rows) -> np.ndarray:
        """``A diag(τ) Aᵀ`` restricted to rows at the same scalar setting (standardised)."""
        A = loc.interp
        same_setting = loc.setting_index[:, None] == loc.setting_index[None, :]
        return (A * self.truncation_variance) @ A.T * same_setting

    def _output(self, mean: Any, cov: Any, lib: Any = np) -> tuple[Any, Any]:
        if not self.log_output:
            return mean, cov
        diag = lib.diagonal(cov) if lib is pt else np.diag(cov)
        half = mean + diag / 2.0
        return lib.exp(half), lib.exp(half[:, None] + half[None, :]) * lib.expm1(cov)

    def _rows(self, inputs: Mapping[str, Any]) -> np.ndarray:
        arrays, _ = self.physics._as_inputs(inputs)
        return np.column_stack([arrays[k] for k in self.physics.inputs])

    def predict_covariance(
        self,
        inputs: Mapping[str, Any],
        params: Mapping[str, float] | Sequence[float],
        without: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean ``(n,)`` and covariance ``(n, n)`` at input rows and one θ.

        ``without`` (a boolean mask over the runs) conditions the weight GPs on the other
        runs only (basis, scaling and hyperparameters kept): what the emulator would
        predict had those curves not been run.

        Examples
        --------
        See :class:`FunctionalEmulator`; ``predict`` returns the diagonal.
        """
        theta = np.array(list(self.physics._as_params(params).values()))
        mean, cov = self._latent_numpy(self._rows(inputs), theta, without)
        return self._output(mean, cov)

    def predict(
        self,
        inputs: Mapping[str, Any],
        params: Mapping[str, float] | Sequence[float],
        without: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean and variance (output units²) at input rows and one θ.

        Examples
        --------
        See :class:`FunctionalEmulator`.
        """
        mean, cov = self.predict_covariance(inputs, params, without)
        return mean, np.diag(cov).copy()

    def at_rows(self, runs: FunctionalRuns, inputs: Mapping[str, Any]) -> np.ndarray:
        """The curves of ``runs`` at input rows, as the emulator reads its grid.

        Each row takes the curve of its scalar setting (``runs`` has one curve per
        setting, e.g. the simulator at one θ) at its functional input(s), linearly
        interpolated between grid points like the emulator's basis.

        Examples
        --------
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> line = PhysicsModel(lambda x, p: p["a"] * x["t"], {"a": Uniform(0, 1)},
        ...                     inputs=["t"])
        >>> grid = {"t": [0.0, 1.0, 2.0]}
        >>> em = FunctionalEmulator(run_curves(line, space_filling_design({"a": (0, 1)}, 6),
        ...                                    grid), line)
        >>> em.at_rows(run_curves(line, pd.DataFrame({"a": [0.5]}), grid), {"t": [0.5, 2.0]})
        array([0.25, 1.  ])
        """
        loc = self._locate(self._rows(inputs))
        scalar = runs.design[list(self.scalar_inputs)].to_numpy(float)
        which = []
        for setting in loc.settings:
            hit = np.flatnonzero(np.all(scalar == setting, axis=1))
            if hit.size == 0:
                named = dict(zip(self.scalar_inputs, setting.tolist(), strict=True))
                raise ValueError(f"at_rows: the runs have no curve at the setting {named}")
            which.append(int(hit[0]))
        curves = np.asarray(runs.curves, dtype=float)[which]
        return np.sum(loc.interp * curves[loc.setting_index], axis=1)

    def parameters_to_unit(self, values: np.ndarray) -> np.ndarray:
        """θ rows (columns in ``runs.parameters`` order) in the unit box of the fit.

        Examples
        --------
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> line = PhysicsModel(lambda x, p: p["a"] * x["t"], {"a": Uniform(0, 1)},
        ...                     inputs=["t"])
        >>> em = FunctionalEmulator(run_curves(line, space_filling_design({"a": (0, 1)}, 6),
        ...                                    {"t": [0.0, 1.0]}), line, box={"a": (0, 1)})
        >>> em.parameters_to_unit(np.array([[0.25]])).tolist(), em.parameters_from_unit([0.5])
        ([[0.25]], array([0.5]))
        """
        values = np.asarray(values, dtype=float)
        rows = np.atleast_2d(values)
        ds = len(self.scalar_inputs)
        H = self._coordinates(np.column_stack([np.ones((len(rows), ds)), rows]))
        unit = (H[:, ds:] - self.lower[ds:]) / self.width[ds:]
        return unit.reshape(values.shape)

    def parameters_from_unit(self, unit: np.ndarray | Sequence[float]) -> np.ndarray:
        """The inverse of :meth:`parameters_to_unit`."""
        ds = len(self.scalar_inputs)
        h = self.lower[ds:] + np.asarray(unit, dtype=float) * self.width[ds:]
        if self.rotation is not None:
            center, matrix = self.rotation
            h = center + np.linalg.solve(matrix, h.T).T
        logs = self.log_columns[ds:]
        return np.where(logs, np.exp(np.where(logs, h, 0.0)), h)

    def predict_curves(self, design: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
        """Latent mean and sd ``(n, P)`` of the curves at every design row, on the grid.

        Latent: ln output with ``log_output=True`` (a Gaussian band there is the
        log-normal band in output units).  On the grid only the diagonal of
        :meth:`predict_covariance` is needed, ``s² (Σ_k Φ_pk² v_k + τ_p)`` with ``v_k``
        the weight GPs' variances at the row, so all rows are predicted at once.

        Examples
        --------
        See :class:`FunctionalEmulator`.
        """
        X = design[list(self.columns)].to_numpy(float)
        Us = (self._coordinates(X) - self.lower) / self.width
        means = np.empty((len(X), self.n_components))
        variances = np.empty((len(X), self.n_components))
        for k, gp in enumerate(self._gps):
            means[:, k], variances[:, k] = gp.predict_each(Us)
        s = self.curve_scale
        mean = self.mean_curve + s * means @ self.basis.T
        var = s**2 * (variances @ (self.basis**2).T + self.truncation_variance)
        return mean, np.sqrt(np.maximum(var, 0.0))

    def held_out(
        self, runs: FunctionalRuns, level: float = 0.9, *, warn: bool = True
    ) -> dict[str, float]:
        """Scores on held-out curves: band coverage, RMSE over sd, mean squared z.

        ``coverage``: share of the held-out grid values inside the central ``level``
        predictive band (in the latent scale, the same band in output units);
        ``rmse_sd``: RMSE of the predictive mean over the sd of the held-out values;
        ``mean_z2``: mean of the squared standardised errors (about 1 when calibrated).
        With ``warn``, an :class:`EmulatorWarning` when the coverage or the RMSE fail the
        limits of :func:`kohpymc.emulator.check_emulator` (over the held-out values).

        Examples
        --------
        >>> import pytensor.tensor as pt
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> decay = PhysicsModel(lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
        ...                      {"a": Uniform(1, 2), "k": Uniform(0.5, 1)}, inputs=["t"])
        >>> box, grid = {"a": (1, 2), "k": (0.5, 1)}, {"t": np.linspace(0, 3, 16)}
        >>> em = FunctionalEmulator(run_curves(decay, space_filling_design(box, 20), grid),
        ...                         decay)
        >>> test = run_curves(decay, space_filling_design(box, 10, method="sobol"), grid)
        >>> bool(em.held_out(test)["rmse_sd"] < 0.01)
        True
        """
        check = self.held_out_check(runs, level)
        z = check.standardized_errors
        scores = {
            "coverage": check.coverage,
            "rmse_sd": check.relative_rmse,
            "mean_z2": float(np.mean(z**2)),
            "n_curves": float(len(runs.curves)),
        }
        if warn and check.problems:
            warn_user(
                f"emulator of {self.physics.name!r} ({len(self.runs.design)} curves) is not "
                "fit for calibration: " + "; ".join(check.problems),
                EmulatorWarning,
            )
        return scores

    def held_out_check(self, runs: FunctionalRuns, level: float = 0.9) -> EmulatorCheck:
        """The held-out curves' grid values scored as an :class:`EmulatorCheck`.

        Simulated values, means and sds are latent (ln output with ``log_output``), one
        per grid point of every held-out curve; ``problems`` as in :meth:`held_out`, the
        coverage's tolerance that of as many independent values as curves
        (:func:`~kohpymc.emulator.checking.coverage_bounds`).  Its
        ``to_dict`` and ``figure`` are those of :func:`kohpymc.emulator.check_emulator`.

        Examples
        --------
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> line = PhysicsModel(lambda x, p: p["a"] * x["t"], {"a": Uniform(0, 1)},
        ...                     inputs=["t"])
        >>> grid = {"t": [0.0, 1.0, 2.0]}
        >>> em = FunctionalEmulator(run_curves(line, space_filling_design({"a": (0, 1)}, 6),
        ...                                    grid), line)
        >>> check = em.held_out_check(run_curves(line, pd.DataFrame({"a": [0.5]}), grid))
        >>> check.kind, check.simulated.size, check.fit
        ('held-out', 3, True)
        """
        mean, sd = self.predict_curves(runs.design)
        truth = np.log(runs.curves) if self.log_output else np.asarray(runs.curves, float)
        check = EmulatorCheck(
            "held-out", truth.ravel(), mean.ravel(), np.maximum(sd, 1e-300).ravel(), level
        )
        # a curve's grid values share its weights' errors: the curves are the
        # independent values of the coverage's binomial tolerance
        check.problems += fit_problems(
            "held-out", check.coverage, check.relative_rmse, len(truth), level=level
        )
        return check

    #: what warnings call its runs
    runs_noun = "curves"

    # ----------------------------------------------------------------- pytensor
    #: evaluate the weight GPs' ``k`` and ``kᵀ K⁻¹ k`` by one compiled op,
    #: :class:`~kohpymc.emulator.quadratic.KernelQuadratic` (``False``: plain PyTensor
    #: products with ``L⁻¹``, the reference it is tested against)
    triangular_op: bool = True

    def _training_values(self) -> dict[str, np.ndarray]:
        """The weight GPs' training data, stacked over the ``K`` GPs."""
        values = {
            "U": self.U,
            "alpha": np.array([gp.alpha for gp in self._gps]),  # (K, N)
            "chol_inv": np.array([gp.chol_inv for gp in self._gps]),  # (K, N, N)
            "lengthscales": np.array([h.lengthscales for h in self.hypers]),  # (K, q)
            "amplitude": np.array([h.amplitude for h in self.hypers]),
            "nugget": np.array([h.nugget for h in self.hypers]),
            "lower": self.lower,
            "width": self.width,
        }
        if self.rotation is not None:
            values["center"], values["matrix"] = self.rotation
        return values

    def _latent_tensor(self, theta: Any, X: np.ndarray, low_rank: bool = False) -> tuple[Any, Any]:
        """Latent mean and covariance at the rows: all K weight GPs as batched tensors.

        With ``low_rank`` the covariance is a :func:`~kohpymc.gaussian.low_rank_covariance`
        whenever its structure allows (see :meth:`_low_rank_factor`), else dense.
        """
        loc = self._locate(X)
        w_mean, cov_w = self._weight_moments(theta, loc)
        B = loc.interp @ self.basis  # (n, K)
        B_t = shared_array(B, "emulator_basis_at_rows")
        idx = loc.setting_index
        trunc = self._truncation(loc)
        s = self.curve_scale
        one = len(loc.settings) == 1
        w_rows = pt.dot(B_t, w_mean[:, 0]) if one else pt.sum(B_t.T * w_mean[:, idx], axis=0)
        mean = shared_array(loc.interp @ self.mean_curve, "emulator_mean_at_rows") + s * w_rows
        factor = self._low_rank_factor(B, B_t, loc, trunc, cov_w) if low_rank else None
        if factor is not None:
            d = shared_array(s**2 * np.diag(trunc), "emulator_truncation_at_rows")
            return mean, low_rank_covariance(d, s * factor)
        if one:
            cov = trunc + pt.dot(B_t * cov_w[:, 0, 0][None, :], B_t.T)
        else:
            outer = B_t.T[:, :, None] * B_t.T[:, None, :]  # (K, n, n)
            cov = trunc + pt.sum(outer * cov_w[:, idx][:, :, idx], axis=0)
        return mean, s**2 * cov

    def _weight_moments(self, theta: Any, loc: _Rows) -> tuple[Any, Any]:
        """GP means ``(K, m)`` and covariances ``(K, m, m)`` of the weights at the settings.

        One setting: the variance is clipped below at the nugget, as in :meth:`_WeightGP.predict`.
        """
        ds = len(self.scalar_inputs)
        t = self._training_tensors()
        theta = pt.as_tensor_variable(theta)
        settings = self._unit_settings(loc.settings)  # (m, d_s) numbers
        m = len(settings)
        LS, amp, nug, U = t["lengthscales"], t["amplitude"], t["nugget"], t["U"]
        # squared distances (K, m, N): the settings' part, then θ's (shared by the settings)
        base = pt.zeros((len(self.hypers), m, self.n_runs))
        if ds:
            diff = (settings[None, :, None, :] - U[None, None, :, :ds]) / LS[:, None, None, :ds]
            base = pt.sum(diff**2, axis=-1)
        u = self._theta_unit_tensor(theta)
        if self.triangular_op:
            Kc, quad, _, _ = kernel_quadratic(
                self.kernel, t["chol_inv"], U[:, ds:], LS[:, ds:], amp, base, u
            )
        else:
            r2 = pt.sum(((U[None, :, ds:] - u[None, None, :]) / LS[:, None, ds:]) ** 2, axis=-1)
            Kc = kernel_values(self.kernel, base + r2[:, None, :], amp[:, None, None], pt)
            V = pt.matmul(t["chol_inv"], Kc.transpose(0, 2, 1))  # (K, N, m)
            quad = pt.matmul(V.transpose(0, 2, 1), V)
        w_mean = pt.sum(Kc * t["alpha"][:, None, :], axis=-1)  # (K, m)
        if m == 1:
            var = pt.maximum(amp + nug - quad[:, 0, 0], nug)  # (K,)
            return w_mean, var[:, None, None]
        gap = (settings[None, :, None, :] - settings[None, None, :, :]) / LS[:, None, None, :ds]
        prior = kernel_values(self.kernel, pt.sum(gap**2, axis=-1), amp[:, None, None], pt)
        return w_mean, prior - quad + nug[:, None, None] * np.eye(m)

    def _low_rank_factor(
        self, B: np.ndarray, B_t: Any, loc: _Rows, trunc: np.ndarray, cov_w: Any
    ) -> Any | None:
        """``F`` ``(n, K m)`` with ``Σ_k (B_k B_kᵀ) ∘ c_k[idx, idx] = F Fᵀ``, or ``None``.

        ``F_k = diag(B_k) E L_k`` with ``E`` the rows' setting indicator and
        ``c_k = L_k L_kᵀ``; ``B`` the basis at the rows and ``B_t`` the same as a
        tensor.  ``None`` (dense) when the output is log-normal, when the truncation
        term is not diagonal (rows sharing a grid point at one setting) or when the
        rank ``K m`` is not below the number of rows.
        """
        n, K, m = B.shape[0], B.shape[1], len(loc.settings)
        if self.log_output or K * m >= n or np.any(trunc[~np.eye(n, dtype=bool)] != 0.0):
            return None
        if m == 1:
            return B_t * pt.sqrt(cov_w[:, 0, 0])[None, :]
        chol = pt.linalg.cholesky(cov_w, lower=True)  # (K, m, m)
        blocks = B_t.T[:, :, None] * chol[:, loc.setting_index, :]  # (K, n, m)
        return blocks.transpose(1, 0, 2).reshape((n, K * m))

    def mean_tensor(self, theta: Any, X: Any) -> Any:
        """Symbolic predictive mean at rows ``X`` (numbers, input order) as a function of θ.

        Examples
        --------
        See :meth:`covariance_tensor`.
        """
        mean, cov = self._latent_tensor(theta, _numbers(X))
        return self._output(mean, cov, pt)[0]

    def covariance_tensor(self, theta: Any, X: Any, low_rank: bool = True) -> Any:
        """Symbolic predictive covariance ``Σ_η(θ)`` ``(n, n)`` between the rows ``X``.

        With ``low_rank`` (default) it is built by
        :func:`~kohpymc.gaussian.low_rank_covariance` (the truncation diagonal plus rank
        ``K m``, ``m`` the rows' distinct scalar settings) whenever that holds: not
        log-normal, no two rows at one grid point and setting, ``K m < n``.  The
        likelihood then uses the Woodbury form; ``low_rank=False`` gives the plain dense
        matrix.

        Examples
        --------
        >>> import pytensor.tensor as pt
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> decay = PhysicsModel(lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
        ...                      {"a": Uniform(1, 2), "k": Uniform(0.5, 1)}, inputs=["t"])
        >>> design = space_filling_design({"a": (1, 2), "k": (0.5, 1)}, 12, seed=1)
        >>> em = FunctionalEmulator(run_curves(decay, design, {"t": [0.0, 1.0, 2.0]}), decay)
        >>> X = np.array([[0.5], [1.5]])
        >>> C = em.covariance_tensor(pt.as_tensor([1.5, 0.7]), X).eval()
        >>> bool(np.allclose(C, em.predict_covariance({"t": [0.5, 1.5]}, [1.5, 0.7])[1]))
        True
        """
        mean, cov = self._latent_tensor(theta, _numbers(X), low_rank)
        return cov if low_rank_parts(cov) else self._output(mean, cov, pt)[1]

    def variance_tensor(self, theta: Any, X: Any) -> Any:
        """Symbolic predictive variance at the rows (the diagonal of the covariance)."""
        cov = self.covariance_tensor(theta, X)
        parts = low_rank_parts(cov)
        if parts is None:
            return pt.diagonal(cov)
        d, F = parts
        return d + pt.sum(F**2, axis=1)

    def support_logp(self, theta: Any, margin: float = 0.0, softness: float = 0.01) -> Any:
        """Log-density term confining θ to the design: 0 inside, quadratic wall outside.

        In the GP coordinates of θ scaled to the runs' unit box (``u``, rotated when
        ``rotation`` is given), ``-½ Σ_i (max(0, |u_i - ½| - ½ - margin) / softness)²``.
        Outside its design the emulator reverts to its mean curve with the GPs' prior
        variance along the basis, a broad likelihood that explains the data about as
        well as the best fit; over a prior box much larger than the design that volume
        would dominate the posterior.  Confining the prior to the design (chosen by a first
        pass to contain the posterior) avoids it.

        Examples
        --------
        >>> import pytensor.tensor as pt
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> decay = PhysicsModel(lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
        ...                      {"a": Uniform(1, 2), "k": Uniform(0.5, 1)}, inputs=["t"])
        >>> design = space_filling_design({"a": (1.2, 1.8), "k": (0.6, 0.9)}, 10, seed=1)
        >>> em = FunctionalEmulator(run_curves(decay, design, {"t": [0.0, 1.0, 2.0]}), decay,
        ...                         box={"a": (1.2, 1.8), "k": (0.6, 0.9)})
        >>> float(em.support_logp(pt.as_tensor([1.5, 0.7])).eval()) == 0
        True
        >>> bool(em.support_logp(pt.as_tensor([1.9, 0.7])).eval() < -100)
        True
        """
        u = self._theta_unit_tensor(pt.as_tensor_variable(theta))
        excess = pt.maximum(pt.abs(u - 0.5) - 0.5 - margin, 0.0)
        return -0.5 * pt.sum((excess / softness) ** 2)

    def _theta_unit_tensor(self, theta: Any) -> Any:
        """θ's GP coordinates scaled to the unit box, as a tensor ``(p,)``."""
        ds = len(self.scalar_inputs)
        t = self._training_tensors()
        logged = self.log_columns[ds:]
        h = pt.where(logged, pt.log(pt.where(logged, theta, 1.0)), theta) if logged.any() else theta
        if self.rotation is not None:
            h = pt.dot(t["matrix"], h - t["center"])
        return (h - t["lower"][ds:]) / t["width"][ds:]

    def physics_model(
        self,
        *,
        covariance: Literal["full", "dense", "diagonal"] = "full",
        name: str | None = None,
        confine: bool = False,
    ) -> FunctionalEmulatedPhysics:
        """The emulator as a physics model (priors of the simulator's parameters).

        Parameters
        ----------
        covariance : {"full", "dense", "diagonal"}
            ``"full"`` (default): ``Σ_η(θ)`` between the calibration rows enters the
            likelihood covariance, as a diagonal plus low rank when it is one (the
            likelihood is then evaluated by the Woodbury identity, see
            :meth:`FunctionalEmulator.covariance_tensor`); ``"dense"``: the same
            ``Σ_η(θ)`` as a plain ``n × n`` matrix (the likelihood factorizes it, for
            comparisons); ``"diagonal"``: only its diagonal, added to the noise variance
            (ignores that the emulator errors of one curve move together, which
            overstates the information in the data).
        name : str, optional
            Default: the simulator's name + " (PCA emulated)".
        confine : bool
            Add :meth:`support_logp` to the model (``compose_model`` makes it a
            ``pm.Potential`` named ``"physics_support"``): the prior confined to the
            design.  Use it when the design covers only part of the prior box.

        Examples
        --------
        >>> import pytensor.tensor as pt
        >>> from kohpymc import PhysicsModel, Uniform
        >>> from kohpymc.emulator import space_filling_design
        >>> decay = PhysicsModel(lambda x, p: p["a"] * np.exp(-p["k"] * x["t"]),
        ...                      {"a": Uniform(1, 2), "k": Uniform(0.5, 1)}, inputs=["t"],
        ...                      name="decay")
        >>> design = space_filling_design({"a": (1, 2), "k": (0.5, 1)}, 12, seed=1)
        >>> em = FunctionalEmulator(run_curves(decay, design, {"t": [0.0, 1.0, 2.0]}), decay)
        >>> em.physics_model().name
        'decay (PCA emulated)'
        """
        if covariance not in ("full", "dense", "diagonal"):
            raise ValueError(
                f"covariance must be 'full', 'dense' or 'diagonal', got {covariance!r}"
            )
        return FunctionalEmulatedPhysics(self, covariance=covariance, name=name, confine=confine)

    def __repr__(self) -> str:
        return (
            f"FunctionalEmulator({self.physics.name!r}, runs={self.n_runs}, grid="
            f"{list(self.functional)} x {len(self.grid)}, components={self.n_components} "
            f"({100 * self.explained:.3g} %), kernel={self.kernel!r}"
            + (", log_output=True)" if self.log_output else ")")
        )


def _numbers(X: Any) -> np.ndarray:
    """The values of rows given as numbers or as a tensor of constants."""
    if isinstance(X, np.ndarray | list | tuple):
        return np.asarray(X, dtype=float)
    X = pt.as_tensor_variable(X)
    if not all(isinstance(v, Constant) for v in graph_inputs([X])):
        raise TypeError(
            "FunctionalEmulator: the input rows must be known numbers (they select "
            "points of the emulator's grid), not a function of random variables"
        )
    # constant folding evaluates the few nodes in Python (compiling a function: ~0.2 s)
    (folded,) = constant_fold([X], raise_not_constant=False)
    return np.asarray(getattr(folded, "data", folded), dtype=float)


class FunctionalEmulatedPhysics(EmulatedPhysics):
    """A physics model whose ``G`` is a :class:`FunctionalEmulator`'s mean.

    An :class:`~kohpymc.emulator.gp.EmulatedPhysics` over the functional emulator (same
    evaluation, Jacobian, variance and covariance), confined to the design on request.

    :meth:`covariance_tensor` is the emulator's full covariance between the calibration
    rows (dense within a curve, low rank plus diagonal in ``"full"`` mode), which
    :func:`kohpymc.model.compose_model` puts into the likelihood covariance of the
    formulations that accept it.

    Examples
    --------
    See :meth:`FunctionalEmulator.physics_model`.
    """

    emulator: FunctionalEmulator  # type: ignore[assignment]  # narrows the base's Emulator

    def __init__(
        self,
        emulator: FunctionalEmulator,
        *,
        covariance: Literal["full", "dense", "diagonal"] = "full",
        name: str | None = None,
        confine: bool = False,
    ) -> None:
        self.confine = bool(confine)
        super().__init__(
            emulator,  # type: ignore[arg-type]  # the same mean/variance/covariance interface
            covariance=covariance,  # type: ignore[arg-type]  # "dense": read by covariance_tensor here
            name=name or f"{emulator.physics.name} (PCA emulated)",
        )

    def fingerprint_parts(self) -> dict[str, Any]:
        """The emulator's training data, basis, scaling and hyperparameters."""
        from kohpymc.fingerprint import physics_fingerprint

        em = self.emulator
        return {
            "simulator": physics_fingerprint(em.physics),
            "kernel": em.kernel,
            "covariance": self.covariance,
            "U": np.asarray(em.U, dtype=float).round(12).tolist(),
            "weights": np.asarray(em.weights, dtype=float).round(12).tolist(),
            "basis": np.asarray(em.basis, dtype=float).round(12).tolist(),
            "grid": em.grid.round(12).tolist(),
            "scaling": [em.lower.tolist(), em.width.tolist(), em.curve_scale],
            "mean_curve": em.mean_curve.round(12).tolist(),
            "hypers": [repr(h) for h in em.hypers],
            "log_output": em.log_output,
            "confine": self.confine,
            "rotation": None if em.rotation is None else [a.tolist() for a in em.rotation],
        }

    def covariance_tensor(self, theta: Any, X: Any) -> Any:
        """``Σ_η(X, θ)``: low-rank form in ``"full"`` mode, dense in ``"dense"``, else None."""
        if self.covariance == "diagonal":
            return None
        return self.emulator.covariance_tensor(theta, X, low_rank=self.covariance == "full")

    def support_logp(self, theta: Any) -> Any:
        """The emulator's :meth:`~FunctionalEmulator.support_logp` when confined, else None."""
        return self.emulator.support_logp(theta) if self.confine else None
