"""Simulator runs at the points of a design: as tasks, cached on disk, failures kept.

:func:`run_design` runs the physics model at every row of a design (input values and
parameter values) through :func:`kohpymc.run_tasks` — in this process by default, on a
Dask cluster with ``workers=`` or ``scheduler=``.  Rows sharing the same θ go to one
task (one simulator call over those inputs, as a solver computes a whole curve per θ).
With ``cache=`` a folder, every finished point is written there as one small JSON file
named by a hash of (input point, simulator identity), atomically; a rerun, or a run of
an extended design, reads those files and only runs the points not there yet.  A
failed run is recorded (with its error) and skipped; it is not retried unless
``retry_failed=True``.

A simulator with several outputs (a :class:`~kohpymc.multi_output.MultiOutputPhysics`,
whose ``evaluate`` returns ``{output: array}``) runs once per task for all of them; each
cached point keeps every output, and :meth:`SimulatorRuns.output` gives one output's
runs as single-output runs (to fit one emulator per output).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from kohpymc.execution import run_tasks
from kohpymc.fingerprint import digest, source_fingerprint
from kohpymc.physics import PhysicsModel
from kohpymc.progress import TaskDisplay
from kohpymc.study_files import write_atomic

if TYPE_CHECKING:
    from kohpymc.multi_output.physics import MultiOutputPhysics

__all__ = ["SimulatorRuns", "point_key", "run_design", "simulator_identity"]


def simulator_identity(physics: PhysicsModel | MultiOutputPhysics, label: str | None = None) -> str:
    """A string naming the simulator for cache keys: its name and its source code.

    The source is the function's own and that of the file defining it
    (:func:`kohpymc.fingerprint.source_fingerprint`), so a changed helper the function
    calls — the solver behind a thin wrapper — runs the design again instead of reusing
    runs of the old simulator; a model made of per-output models hashes each output's
    function.  ``label`` (e.g. a version of an external solver) replaces the source when
    given.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> simulator_identity(beam.physics_model(), label="v1")
    'euler_bernoulli:v1'
    """
    if label is not None:
        return f"{physics.name}:{label}"
    function = physics.function
    if function is None:  # a multi-output model made of per-output models
        models = getattr(physics, "models", {})
        source = digest({k: source_fingerprint(m.function) for k, m in models.items()})
    else:
        source = source_fingerprint(function)
    return f"{physics.name}:{source[:16]}"


def point_key(point: Mapping[str, float], simulator: str) -> str:
    """The cache key of one run: a hash of the point's values (to 17 digits) and simulator.

    Examples
    --------
    >>> point_key({"x": 1.0, "E": 200.0}, "beam") == point_key({"E": 200.0, "x": 1.0}, "beam")
    True
    """
    text = json.dumps(
        {"simulator": simulator, "point": {k: repr(float(point[k])) for k in sorted(point)}},
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:32]


@dataclass
class SimulatorRuns:
    """The runs of a design: points with outputs, failures, and what ran this time.

    Attributes
    ----------
    points : pandas.DataFrame
        Successful runs: the design's columns plus ``"output"`` (or, for a simulator
        with several outputs, one column per output).
    failed : pandas.DataFrame
        Failed runs: the design's columns plus ``"error"``.
    inputs, parameters : tuple of str
        Which columns are physics inputs and which are parameters.
    simulated : int
        Points run by the simulator in this call (not read from the cache).
    cached : int
        Points read from the cache.
    seconds : float
        Wall time of the simulator tasks run in this call (summed over tasks).
    outputs : tuple of str
        The output columns of a simulator with several outputs (empty: one output).

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> import pandas as pd
    >>> runs = run_design(beam.physics_model(),
    ...                   pd.DataFrame({"x": [400.0], "P": [2.5], "E": [200.0]}))
    >>> runs.points["output"].tolist(), runs.simulated
    ([12.0], 1)
    """

    points: pd.DataFrame
    failed: pd.DataFrame
    inputs: tuple[str, ...]
    parameters: tuple[str, ...]
    simulated: int = 0
    cached: int = 0
    seconds: float = 0.0
    outputs: tuple[str, ...] = ()

    def output(self, name: str) -> SimulatorRuns:
        """One output of a simulator with several outputs, as single-output runs.

        Examples
        --------
        >>> from kohpymc.examples import beam_multi_output as bm
        >>> design = pd.DataFrame({"x": [250.0], "P": [6.0], "E": [200.0]})
        >>> runs = run_design(bm.physics_model(), design)
        >>> runs.output("u").y.round(6).tolist(), runs.simulated
        ([600.0], 1)
        """
        if name not in self.outputs:
            raise KeyError(f"no output {name!r} in these runs; outputs are {list(self.outputs)}")
        columns = list(self.inputs + self.parameters)
        points = self.points[[*columns, name]].rename(columns={name: "output"})
        return replace(self, points=points.reset_index(drop=True), outputs=())

    def failure_summary(self) -> str:
        """``"3 of 40 simulator runs failed (first: ...)"``, or ``""`` when none failed.

        Examples
        --------
        >>> from kohpymc.examples import beam
        >>> runs = run_design(beam.physics_model(),
        ...                   pd.DataFrame({"x": [400.0], "P": [2.5], "E": [200.0]}))
        >>> runs.failure_summary()
        ''
        """
        if not len(self.failed):
            return ""
        total = len(self.failed) + len(self.points)
        first = str(self.failed["error"].iloc[0])
        where = self._failed_region()
        return f"{len(self.failed)} of {total} simulator runs failed{where} (first: {first})"

    def _failed_region(self) -> str:
        """Where the failed runs lie (``""`` when the failures are spread out).

        Each parameter whose failed values span less than half the range of all runs'
        values is named with that span.

        Examples
        --------
        >>> points = pd.DataFrame({"x": [0.0, 1.0], "k": [0.1, 0.5], "output": [1.0, 2.0]})
        >>> failed = pd.DataFrame({"x": [0.5, 0.7], "k": [0.9, 1.0], "error": ["NaN", "NaN"]})
        >>> SimulatorRuns(points, failed, ("x",), ("k",))._failed_region()
        ' where k in [0.9, 1] (all runs: [0.1, 1])'
        """
        named = []
        for name in self.parameters:
            bad = self.failed[name].to_numpy(float)
            every = np.concatenate([bad, self.points[name].to_numpy(float)])
            span = every.max() - every.min()
            if span > 0 and bad.max() - bad.min() < 0.5 * span:
                named.append(
                    f"{name} in [{bad.min():.4g}, {bad.max():.4g}] "
                    f"(all runs: [{every.min():.4g}, {every.max():.4g}])"
                )
        return f" where {', '.join(named)}" if named else ""

    @property
    def X(self) -> np.ndarray:
        """``(n, d + p)``: input columns, then parameter columns, of the successful runs."""
        return self.points[list(self.inputs + self.parameters)].to_numpy(float)

    @property
    def y(self) -> np.ndarray:
        """``(n,)`` simulator outputs of the successful runs (one output only)."""
        if self.outputs:
            raise ValueError(
                f"these runs have outputs {list(self.outputs)}: take one with .output(name)"
            )
        return self.points["output"].to_numpy(float)


def _simulate(key: str, item: tuple[PhysicsModel, dict[str, list[float]], dict[str, float]]):
    """One task: the simulator at one θ over a set of input rows."""
    physics, inputs, params = item
    value = physics.evaluate(inputs, params)
    if isinstance(value, Mapping):  # several outputs from one run
        return {k: np.asarray(v, dtype=float).tolist() for k, v in value.items()}
    return np.asarray(value, dtype=float).tolist()


def _write_record(path: Path, record: dict[str, Any]) -> None:
    text = json.dumps(record)

    def write(tmp: Path) -> None:
        tmp.write_text(text)

    write_atomic(path, write)


def _read_cache(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def run_design(
    physics: PhysicsModel | MultiOutputPhysics,
    design: pd.DataFrame,
    *,
    cache: str | Path | None = None,
    simulator_label: str | None = None,
    retry_failed: bool = False,
    workers: int = 1,
    scheduler: Any = None,
    progress: TaskDisplay | None = None,
) -> SimulatorRuns:
    """Run the simulator at every row of ``design`` (cached, failures recorded).

    Parameters
    ----------
    physics : PhysicsModel or MultiOutputPhysics
        The simulator: ``physics.evaluate(inputs, params)`` (one array, or a mapping
        output -> array for several outputs).
    design : pandas.DataFrame
        One column per physics input and per parameter (e.g. from
        :func:`~kohpymc.emulator.design.space_filling_design`).
    cache : str or Path, optional
        Folder of cached runs (created when missing); without it nothing is cached.
    simulator_label : str, optional
        Names the simulator's version in the cache keys instead of its source code.
    retry_failed : bool
        Run again points whose cached run failed.
    workers, scheduler, progress :
        Where the tasks run, as for :func:`kohpymc.run_tasks`.

    Returns
    -------
    SimulatorRuns

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import beam
    >>> design = pd.DataFrame({"x": [200.0, 400.0], "P": [2.5, 2.5], "E": [200.0, 200.0]})
    >>> folder = tempfile.mkdtemp()
    >>> run_design(beam.physics_model(), design, cache=folder).simulated
    2
    >>> run_design(beam.physics_model(), design, cache=folder).simulated
    0
    """
    inputs, params = tuple(physics.inputs), tuple(physics.parameters)
    columns = list(inputs + params)
    outputs = tuple(getattr(physics, "outputs", ()))  # several outputs: MultiOutputPhysics
    values = _design_values(physics, design, columns)
    simulator = simulator_identity(physics, simulator_label)
    folder = _cache_folder(cache)
    records, order, todo, cached = _plan_points(
        values, columns, params, simulator, folder, retry_failed, outputs
    )
    items = _theta_tasks(physics, todo, records, inputs, params)
    simulated, seconds = _run_theta_tasks(
        items, records, folder, workers, scheduler, progress, outputs
    )
    ok, bad = _split_records(records, order, columns, outputs)
    return SimulatorRuns(
        points=pd.DataFrame(ok, columns=[*columns, *(outputs or ("output",))]),
        failed=pd.DataFrame(bad, columns=[*columns, "error"]),
        inputs=inputs,
        parameters=params,
        simulated=simulated,
        cached=cached,
        seconds=seconds,
        outputs=outputs,
    )


def _design_values(
    physics: PhysicsModel | MultiOutputPhysics, design: pd.DataFrame, columns: list[str]
) -> np.ndarray:
    """The design's ``columns`` as a finite float array (a missing column is a KeyError)."""
    missing = [k for k in columns if k not in design.columns]
    if missing:
        raise KeyError(
            f"run_design: the design lacks column(s) {missing} of {physics.name!r} "
            f"(needs inputs {list(physics.inputs)} and parameters {list(physics.parameters)})"
        )
    values = design[columns].to_numpy(float)
    if not np.all(np.isfinite(values)):
        raise ValueError("run_design: the design contains NaN/inf")
    return values


def _cache_folder(cache: str | Path | None) -> Path | None:
    """The cache folder (created when missing), or None without a cache."""
    folder = None if cache is None else Path(cache)
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
    return folder


def _plan_points(
    values: np.ndarray,
    columns: list[str],
    params: tuple[str, ...],
    simulator: str,
    folder: Path | None,
    retry_failed: bool,
    outputs: tuple[str, ...] = (),
) -> tuple[dict[str, dict[str, Any]], list[str], dict[tuple[float, ...], list[str]], int]:
    """Records of the design's points: cached ones read, the others grouped by θ to run.

    Returns the records (key -> ``{"point", "output", "error", ...}``; ``"outputs"``,
    a mapping, for several outputs), the key of every design row in order, the keys to
    run per θ, and the number of points read from cache.  A cached point without one of
    ``outputs`` runs again.
    """
    records: dict[str, dict[str, Any]] = {}  # key -> {"point", "output", "error"}
    order: list[str] = []
    todo: dict[tuple[float, ...], list[str]] = {}
    cached = 0
    for row in values:
        point = dict(zip(columns, row.tolist(), strict=True))
        key = point_key(point, simulator)
        order.append(key)
        if key in records or any(key in keys for keys in todo.values()):
            continue
        hit = None if folder is None else _read_cache(folder / f"{key}.json")
        if hit is not None and _usable(hit, outputs, retry_failed):
            records[key] = hit
            cached += 1
            continue
        theta = tuple(point[k] for k in params)
        todo.setdefault(theta, []).append(key)
        records[key] = {"point": point, "output": None, "error": None, "simulator": simulator}
    return records, order, todo, cached


def _usable(hit: dict[str, Any], outputs: tuple[str, ...], retry_failed: bool) -> bool:
    """Whether a cached record serves: a failure (unless retried) or every output wanted."""
    if hit.get("error") is not None:
        return not retry_failed
    if not outputs:
        return hit.get("output") is not None
    values = hit.get("outputs")
    return isinstance(values, dict) and all(k in values for k in outputs)


def _theta_tasks(
    physics: PhysicsModel | MultiOutputPhysics,
    todo: dict[tuple[float, ...], list[str]],
    records: dict[str, dict[str, Any]],
    inputs: tuple[str, ...],
    params: tuple[str, ...],
) -> dict[str, tuple[Any, ...]]:
    """One task per θ: name -> (physics, input columns, θ, keys of its points)."""
    items = {}
    for t, (theta, keys) in enumerate(todo.items()):
        rows = [records[k]["point"] for k in keys]
        x = {name: [r[name] for r in rows] for name in inputs}
        items[f"run-{t}"] = (physics, x, dict(zip(params, theta, strict=True)), keys)
    return items


def _run_theta_tasks(
    items: dict[str, tuple[Any, ...]],
    records: dict[str, dict[str, Any]],
    folder: Path | None,
    workers: int,
    scheduler: Any,
    progress: TaskDisplay | None,
    outputs: tuple[str, ...] = (),
) -> tuple[int, float]:
    """Run the tasks, filling their points' records (and cache files); (points run, seconds)."""
    tasks = {name: item[:3] for name, item in items.items()}
    seconds = 0.0
    simulated = 0
    for outcome in run_tasks(
        _simulate, tasks, workers=workers, scheduler=scheduler, progress=progress
    ):
        keys = items[outcome.key][3]
        seconds += outcome.seconds
        simulated += len(keys)
        for j, key in enumerate(keys):
            rec = records[key]
            if outcome.error is None and outputs:
                values = {k: float(outcome.value[k][j]) for k in outputs}
                rec["outputs"], rec["error"] = values, None
            elif outcome.error is None:
                rec["output"], rec["error"] = float(outcome.value[j]), None
            else:
                rec["output"], rec["error"] = None, outcome.error
            if folder is not None:
                _write_record(folder / f"{key}.json", rec)
    return simulated, seconds


def _split_records(
    records: dict[str, dict[str, Any]],
    order: list[str],
    columns: list[str],
    outputs: tuple[str, ...] = (),
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Rows of the successful and of the failed points, in design order (once each)."""
    ok, bad = [], []
    for key in dict.fromkeys(order):
        rec = records[key]
        row = {k: rec["point"][k] for k in columns}
        if rec.get("error") is None and outputs:
            ok.append({**row, **{k: float(rec["outputs"][k]) for k in outputs}})
        elif rec.get("error") is None and rec.get("output") is not None:
            ok.append({**row, "output": float(rec["output"])})
        else:
            bad.append({**row, "error": str(rec.get("error"))})
    return ok, bad
