"""Space-filling designs over the calibration inputs × the prior box of θ.

A design is a :class:`pandas.DataFrame` with one column per physics input and per
parameter, one row per simulator run.  :func:`design_box` gives the box (the range of
the calibration inputs and :func:`kohpymc.prior_box` of θ), :func:`space_filling_design`
fills it (a Latin hypercube optimised for the maximin distance, a plain one, or a
scrambled Sobol sequence), and :func:`extend_design` adds points far from those already
run (greedy maximin over a candidate pool), so an extended design reuses every earlier
run.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Literal

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.initialization import prior_box
from kohpymc.physics import PhysicsModel

__all__ = [
    "DESIGNS",
    "Box",
    "design_box",
    "extend_design",
    "maximin_distance",
    "space_filling_design",
]

#: column name -> (lower, upper)
Box = Mapping[str, tuple[float, float]]

#: the design methods :func:`space_filling_design` knows
DESIGNS = ("maximin-lhs", "lhs", "sobol")

DesignMethod = Literal["maximin-lhs", "lhs", "sobol"]


def design_box(
    physics: PhysicsModel,
    data: CalibrationData | None = None,
    *,
    inputs: Box | None = None,
    bounds: Box | None = None,
    coverage: float = 0.99,
) -> dict[str, tuple[float, float]]:
    """The box a design fills: calibration inputs, then the physics parameters.

    Parameters
    ----------
    physics : PhysicsModel
        Its inputs and parameters name the columns; θ's box is
        :func:`kohpymc.prior_box` (``bounds`` and ``coverage`` are passed on).
    data : CalibrationData, optional
        The calibration data; each input's box is its range in the data.
    inputs : mapping, optional
        Input name -> ``(lower, upper)``, overriding (or, without data, giving) the
        input boxes.  An input with ``lower == upper`` is constant.

    Returns
    -------
    dict
        Column name -> ``(lower, upper)``: the physics inputs in order, then θ.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> box = design_box(beam.physics_model(), beam.generate_data(seed=1))
    >>> list(box), box["E"]
    (['x', 'P', 'E'], (50.0, 300.0))
    """
    inputs = dict(inputs or {})
    box: dict[str, tuple[float, float]] = {}
    for name in physics.inputs:
        if name in inputs:
            lo, hi = inputs[name]
        elif data is not None and name in data.inputs:
            col = np.asarray(data.inputs[name], dtype=float)
            lo, hi = float(np.min(col)), float(np.max(col))
        else:
            raise KeyError(
                f"design_box: no range for input {name!r} of {physics.name!r}; give the "
                f"calibration data or inputs={{{name!r}: (lower, upper)}}"
            )
        lo, hi = float(lo), float(hi)
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ValueError(f"design_box: input {name!r} has no finite range [{lo}, {hi}]")
        box[name] = (lo, hi)
    box.update(prior_box(physics, coverage=coverage, bounds=bounds))
    return box


def _check_box(box: Box) -> tuple[list[str], np.ndarray, np.ndarray]:
    if not box:
        raise ValueError("design box is empty: give at least one column")
    names = [str(k) for k in box]
    lo = np.array([float(box[k][0]) for k in box])
    hi = np.array([float(box[k][1]) for k in box])
    bad = [k for k, a, b in zip(names, lo, hi, strict=True) if not (np.isfinite(a) and b >= a)]
    if bad or not np.all(np.isfinite(hi)):
        raise ValueError(f"design box: column(s) {bad} have no finite range (lower <= upper)")
    return names, lo, hi


#: a positive column whose upper bound is this many times its lower one is scaled in logs
DECADES_RATIO = 100.0


def log_scaled(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which columns of a box are spread on a log scale: positive and two decades or more.

    A prior box such as A in (e^12, e^20) for an Arrhenius prefactor puts nearly every
    point of a linear design in its top decade; designs and the emulator's unit box use
    ln x for such columns instead.

    Examples
    --------
    >>> log_scaled(np.array([1e3, 0.0, 50.0]), np.array([1e8, 1.0, 300.0])).tolist()
    [True, False, False]
    """
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return (lo > 0) & (hi / np.where(lo > 0, lo, 1.0) >= DECADES_RATIO)


def to_unit(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Rows of a box mapped to the unit box (log scale for :func:`log_scaled` columns).

    Examples
    --------
    >>> to_unit(np.array([[1e5, 0.5]]), np.array([1e3, 0.0]), np.array([1e7, 1.0])).tolist()
    [[0.5, 0.5]]
    """
    logs = log_scaled(lo, hi)
    a, b = np.where(logs, np.log(np.where(logs, lo, 1.0)), lo), np.where(logs, np.log(hi), hi)
    width = np.where(b > a, b - a, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(logs, np.log(np.where(logs, values, 1.0)), values)
    return (x - a) / width


def from_unit(unit: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The inverse of :func:`to_unit`.

    Examples
    --------
    >>> from_unit(np.array([[0.5, 0.5]]), np.array([1e3, 0.0]), np.array([1e7, 1.0])).round(6)
    array([[1.e+05, 5.e-01]])
    """
    logs = log_scaled(lo, hi)
    a, b = np.where(logs, np.log(np.where(logs, lo, 1.0)), lo), np.where(logs, np.log(hi), hi)
    x = a + unit * (b - a)
    return np.where(logs, np.exp(np.where(logs, x, 0.0)), x)


def maximin_distance(points: np.ndarray) -> float:
    """The smallest distance between two rows of ``points`` (the maximin criterion).

    Examples
    --------
    >>> maximin_distance(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.5]]))
    0.5
    """
    points = np.asarray(points, dtype=float)
    if points.shape[0] < 2:
        return float("inf")
    sq = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=-1)
    np.fill_diagonal(sq, np.inf)
    return float(np.sqrt(np.min(sq)))


def _lhs(n: int, d: int, rng: np.random.Generator) -> np.ndarray:
    from scipy.stats import qmc

    return qmc.LatinHypercube(d, seed=rng).random(n)


def _maximin_lhs(n: int, d: int, rng: np.random.Generator, tries: int, sweeps: int) -> np.ndarray:
    """Best of ``tries`` Latin hypercubes, then swaps of one coordinate of the closest pair.

    A swap of column entries keeps the Latin-hypercube property; it is kept when the
    smallest pairwise distance grows.
    """
    best = min((_lhs(n, d, rng) for _ in range(max(1, tries))), key=maximin_distance)
    if n < 3:
        return best
    sq = np.sum((best[:, None, :] - best[None, :, :]) ** 2, axis=-1)
    np.fill_diagonal(sq, np.inf)
    current = float(np.min(sq))
    for _ in range(sweeps * n):
        i, j = np.unravel_index(int(np.argmin(sq)), sq.shape)
        a = int(i if rng.random() < 0.5 else j)
        b = int(rng.integers(n))
        if b in (i, j):
            continue
        col = int(rng.integers(d))
        trial = best.copy()
        trial[[a, b], col] = trial[[b, a], col]
        rows = trial[[a, b]]
        new = np.sum((rows[:, None, :] - trial[None, :, :]) ** 2, axis=-1)
        trial_sq = sq.copy()
        trial_sq[[a, b], :] = new
        trial_sq[:, [a, b]] = new.T
        np.fill_diagonal(trial_sq, np.inf)
        value = float(np.min(trial_sq))
        if value > current:
            best, sq, current = trial, trial_sq, value
    return best


def _sobol(n: int, d: int, rng: np.random.Generator) -> np.ndarray:
    from scipy.stats import qmc

    m = int(np.ceil(np.log2(max(n, 1))))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # balance warning: we take a prefix
        return qmc.Sobol(d, scramble=True, seed=rng).random_base2(m)[:n]


def _unit_points(n: int, d: int, method: str, rng: np.random.Generator) -> np.ndarray:
    if method == "maximin-lhs":
        return _maximin_lhs(n, d, rng, tries=20, sweeps=20)
    if method == "lhs":
        return _lhs(n, d, rng)
    if method == "sobol":
        return _sobol(n, d, rng)
    raise ValueError(f"design method must be one of {list(DESIGNS)}, got {method!r}")


def space_filling_design(
    box: Box, n: int, *, method: DesignMethod = "maximin-lhs", seed: int = 0
) -> pd.DataFrame:
    """``n`` space-filling points in a box.

    Parameters
    ----------
    box : mapping
        Column name -> ``(lower, upper)`` (e.g. from :func:`design_box`).
    n : int
        Number of points (simulator runs), at least 1.
    method : {"maximin-lhs", "lhs", "sobol"}
        A Latin hypercube improved for the maximin distance (the best of 20, then
        coordinate swaps that widen the closest pair), a plain Latin hypercube, or the
        first ``n`` points of a scrambled Sobol sequence.  Columns spanning two decades
        or more (positive) are spread on a log scale (:func:`log_scaled`).
    seed : int
        Random seed.

    Returns
    -------
    pandas.DataFrame
        ``n`` rows, the box's columns.

    Examples
    --------
    >>> d = space_filling_design({"x": (0, 1), "k": (2, 4)}, 10, seed=1)
    >>> d.shape, bool(d["k"].between(2, 4).all())
    ((10, 2), True)
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"a design needs at least one point, got n={n}")
    names, lo, hi = _check_box(box)
    rng = np.random.default_rng(seed)
    unit = _unit_points(n, len(names), method, rng)
    return pd.DataFrame(from_unit(unit, lo, hi), columns=names)


def extend_design(
    design: pd.DataFrame,
    box: Box,
    n_new: int,
    *,
    seed: int = 0,
    pool: int = 20,
) -> pd.DataFrame:
    """``design`` with ``n_new`` points added far from the points it holds.

    The new points are picked one at a time from ``pool × n_new`` Latin-hypercube
    candidates, each the candidate farthest (in the unit box) from every point chosen
    so far; the earlier rows are kept as they are, so their cached runs are reused.

    Examples
    --------
    >>> box = {"x": (0, 1), "k": (2, 4)}
    >>> first = space_filling_design(box, 8, seed=1)
    >>> more = extend_design(first, box, 4, seed=2)
    >>> len(more), bool((more.iloc[:8] == first).all().all())
    (12, True)
    """
    names, lo, hi = _check_box(box)
    missing = [k for k in names if k not in design.columns]
    if missing:
        raise KeyError(f"extend_design: the design lacks column(s) {missing}")
    n_new = int(n_new)
    if n_new < 0:
        raise ValueError(f"n_new must be >= 0, got {n_new}")
    old = to_unit(design[names].to_numpy(float), lo, hi)
    rng = np.random.default_rng(seed)
    candidates = _lhs(max(pool * n_new, n_new), len(names), rng)
    chosen: list[np.ndarray] = []
    if len(old):
        nearest = np.min(np.sum((candidates[:, None] - old[None]) ** 2, axis=-1), axis=1)
    else:
        nearest = np.full(len(candidates), np.inf)
    for _ in range(n_new):
        k = int(np.argmax(nearest))
        chosen.append(candidates[k])
        nearest = np.minimum(nearest, np.sum((candidates - candidates[k]) ** 2, axis=1))
        nearest[k] = -1.0
    new = pd.DataFrame(from_unit(np.array(chosen).reshape(-1, len(names)), lo, hi), columns=names)
    return pd.concat([design[names], new], ignore_index=True)
