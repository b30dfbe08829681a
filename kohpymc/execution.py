"""Where tasks run: in this process, on a local Dask cluster, or on an existing one.

:func:`run_tasks` runs ``function(key, item)`` for every item of a mapping and yields a
:class:`TaskOutcome` per task as each finishes:

* neither ``workers > 1`` nor ``scheduler``: one after the other in this process (Dask is
  not imported);
* ``workers=N``: on a ``dask.distributed.LocalCluster`` of N single-threaded worker
  processes, started here and closed at the end (also on an error or Ctrl-C);
* ``scheduler="tcp://HOST:PORT"`` (or a ``distributed.Client``): on an existing cluster
  (``dask scheduler`` / ``dask worker``, dask-jobqueue), which is left running.

On a cluster, at most one kohpymc task runs in a worker process at a time (PyTensor's
compilation is not thread-safe) and every worker process compiles into its own PyTensor
compile directory (:func:`compile_dir_plugin`; processes sharing one corrupt or lock each
other's cache, pymc issue 7819).  A task whose worker dies (killed by the OS, a crash in
compiled code) becomes that task's failure; the others go on.  Results come back to the
caller, which alone writes files.  The function and the items travel with ``cloudpickle``:
functions of installed modules by reference, those of modules registered with
:func:`ship_by_value` (a physics file named in a study file) by value.
"""

from __future__ import annotations

import itertools
import logging
import os
import socket
import threading
import time
import uuid
import warnings
from collections.abc import Callable, Generator, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

from kohpymc.checks import check_execution
from kohpymc.progress import TaskDisplay, reporting_to
from kohpymc.warning_filters import warn_user

__all__ = [
    "TaskOutcome",
    "compile_dir_plugin",
    "run_tasks",
    "runs_remotely",
    "ship_by_value",
    "worker_compile_dir",
]

#: failures a worker death may cause to one task before it is that task's failure (the
#: scheduler's ``distributed.scheduler.allowed-failures``, default 3: a deterministic crash
#: would kill four workers in turn)
ALLOWED_FAILURES = 0

#: what a worker death means, in the task's failure message
_DIED = (
    "its Dask worker process died while running it (killed by the operating system, e.g. "
    "out of memory, or a crash in compiled code)"
)


@dataclass(frozen=True)
class TaskOutcome:
    """One finished task.

    Attributes
    ----------
    key : str
        The item's key.
    value : object
        What the function returned (None when it failed).
    error : str or None
        Why it failed: ``"TypeName: message"`` of the exception it raised, or a message
        saying its worker died.
    seconds : float
        Wall time of the task where it ran.
    where : str
        ``"local"`` or the worker's address.
    """

    key: str
    value: Any = None
    error: str | None = None
    seconds: float = 0.0
    where: str = "local"


def runs_remotely(workers: int = 1, scheduler: Any = None) -> bool:
    """Whether :func:`run_tasks` with these settings runs tasks on a Dask cluster.

    Examples
    --------
    >>> runs_remotely(1), runs_remotely(2), runs_remotely(scheduler="tcp://10.0.0.1:8786")
    (False, True, True)
    """
    return workers > 1 or scheduler is not None


def run_tasks(
    function: Callable[[str, Any], Any],
    items: Mapping[str, Any],
    *,
    workers: int = 1,
    scheduler: Any = None,
    progress: TaskDisplay | None = None,
) -> Generator[TaskOutcome, None, None]:
    """Run ``function(key, item)`` for every item; yield outcomes as tasks finish.

    An exception raised by ``function`` becomes the task's :attr:`TaskOutcome.error`
    and the other tasks go on (``KeyboardInterrupt`` stops everything).

    Parameters
    ----------
    function : callable
        ``function(key, item) -> value``.  On a cluster, ``function``, the items and the
        values must pickle (``cloudpickle``).
    items : mapping key -> item
        The tasks, started in this order.
    workers : int
        More than 1: start a local cluster of this many worker processes.
    scheduler : str or distributed.Client, optional
        Address (``"tcp://HOST:PORT"``) or client of an existing cluster.
    progress : TaskDisplay, optional
        Told when tasks are queued, run, change phase (:func:`kohpymc.report_phase`),
        finish or fail.

    Yields
    ------
    TaskOutcome
        In the order the tasks finish.

    Examples
    --------
    >>> outcomes = run_tasks(lambda key, x: 1 / x, {"a": 2.0, "b": 0.0})
    >>> [(o.key, o.value, o.error) for o in outcomes]
    [('a', 0.5, None), ('b', None, 'ZeroDivisionError: float division by zero')]
    """
    check_execution(workers, scheduler)
    display = progress or TaskDisplay()
    display.queued(list(items))
    if runs_remotely(workers, scheduler):
        yield from _run_on_cluster(function, items, workers, scheduler, display)
    else:
        yield from _run_here(function, items, display)


def _describe(err: BaseException) -> str:
    return f"{type(err).__name__}: {err}"


def _call(function: Callable[[str, Any], Any], key: str, item: Any) -> tuple[Any, str | None]:
    """``(value, None)`` or ``(None, error message)``."""
    try:
        return function(key, item), None
    except Exception as err:  # noqa: BLE001 - the task's failure, the others go on
        return None, _describe(err)


def _run_here(function, items: Mapping[str, Any], display: TaskDisplay) -> Iterator[TaskOutcome]:
    """One task after the other in this process."""
    for key, item in items.items():
        display.running(key)
        start = time.perf_counter()

        def report(kind: str, text: str, key: str = key) -> None:
            (display.phase if kind == "phase" else display.note)(key, text)

        with reporting_to(report):
            value, error = _call(function, key, item)
        outcome = TaskOutcome(key, value, error, time.perf_counter() - start)
        _tell(display, outcome)
        yield outcome


def _tell(display: TaskDisplay, outcome: TaskOutcome) -> None:
    if outcome.error is None:
        display.done(outcome.key, outcome.seconds)
    else:
        display.failed(outcome.key, outcome.error)


# ---------------------------------------------------------------------------------------
# on a Dask cluster


def ship_by_value(module: ModuleType) -> None:
    """Send the functions of ``module`` to Dask workers by value, not by import.

    For modules the workers cannot import, such as a physics file loaded from a path by
    :func:`kohpymc.load_study` (``function = "physics.py:model"``).

    Examples
    --------
    >>> import types, sys
    >>> module = types.ModuleType("kohpymc_example_physics")
    >>> sys.modules[module.__name__] = module
    >>> ship_by_value(module)
    """
    import cloudpickle

    if module.__name__ not in cloudpickle.list_registry_pickle_by_value():
        cloudpickle.register_pickle_by_value(module)


@contextmanager
def _client(workers: int, scheduler: Any) -> Iterator[Any]:
    """A client of the cluster: started here (and closed) or existing (left running)."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None and not isinstance(scheduler, str):
        yield scheduler  # the caller's client: neither it nor its cluster is closed here
        return
    if scheduler is not None:
        try:
            # waits up to Dask's distributed.comm.timeouts.connect (default 30 s)
            client = Client(scheduler, set_as_default=False)
        except OSError as err:
            raise ConnectionError(f"cannot reach the Dask scheduler {scheduler!r}: {err}") from err
        with client:
            yield client
        return
    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES}):
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True,
            dashboard_address=":0", silence_logs=logging.CRITICAL,
        )  # fmt: skip
    try:
        with Client(cluster, set_as_default=False) as client:
            yield client
    finally:
        cluster.close()


def _run_on_cluster(function, items, workers, scheduler, display) -> Iterator[TaskOutcome]:
    """Submit the tasks (no more at a time than there are workers); yield as they finish."""
    import cloudpickle
    from distributed import as_completed

    shipped = cloudpickle.dumps(function)
    topic = f"kohpymc-progress-{uuid.uuid4().hex}"
    levels = _logger_levels()
    with _client(workers, scheduler) as client:
        client.register_plugin(compile_dir_plugin(), name="kohpymc-compile-dir")
        client.subscribe_topic(topic, lambda event: _relay(display, event[1]))
        waiting = list(items)
        submitted: dict[Any, tuple[str, float]] = {}
        finished = as_completed(loop=client.loop)

        def submit_more() -> None:
            room = max(1, len(client.nthreads())) - finished.count()
            while waiting and room > 0:
                key = waiting.pop(0)
                future = client.submit(
                    _remote_call, shipped, key, cloudpickle.dumps(items[key]), topic, levels,
                    key=f"kohpymc-{key}-{uuid.uuid4().hex[:8]}", pure=False,
                )  # fmt: skip
                submitted[future] = (key, time.perf_counter())
                finished.add(future)
                room -= 1

        try:
            submit_more()
            for future in finished:
                key, since = submitted[future]
                outcome = _outcome(future, key, time.perf_counter() - since)
                _tell(display, outcome)
                submit_more()
                yield outcome
        finally:
            client.cancel(list(submitted))
            client.unsubscribe_topic(topic)


def _relay(display: TaskDisplay, message: dict[str, str]) -> None:
    """A worker's progress event to the display (runs on the client's event loop)."""
    kind, key, text = message["kind"], message["key"], message["text"]
    if kind == "running":
        display.running(key)
    elif kind == "phase":
        display.phase(key, text)
    else:
        display.note(key, text)


def _outcome(future: Any, key: str, waited: float) -> TaskOutcome:
    """What came back: a result, the function's error, or a dead worker."""
    from distributed.scheduler import KilledWorker

    if future.status == "finished":
        try:
            remote: _Remote = future.result()
        except Exception as lost:  # noqa: BLE001 - e.g. a value that does not unpickle here
            return TaskOutcome(key, None, f"bringing its result back: {_describe(lost)}", waited)
        for category, message, filename, lineno in remote.warnings:
            warnings.warn_explicit(message, category, filename, lineno)
        return TaskOutcome(key, remote.value, remote.error, remote.seconds, remote.where)
    if future.status == "cancelled":
        return TaskOutcome(key, None, "cancelled: the Dask scheduler dropped it", waited)
    err = future.exception()
    if isinstance(err, KilledWorker):
        where = getattr(getattr(err, "last_worker", None), "address", "")
        return TaskOutcome(key, None, _DIED, waited, where)
    return TaskOutcome(key, None, f"on a Dask worker: {_describe(err)}", waited)


@dataclass
class _Remote:
    """A task's result as it travels back from a worker."""

    value: Any
    error: str | None
    seconds: float
    where: str
    warnings: list[tuple[type[Warning], str, str, int]] = field(default_factory=list)


#: one kohpymc task at a time per worker process (PyTensor's compilation is not thread-safe)
_ONE_AT_A_TIME = threading.Lock()


def _logger_levels() -> dict[str, int]:
    """The levels set on this process's loggers (Dask's own excepted), for the workers.

    A task's libraries then log on a worker what they would log here: a command that
    silenced PyMC's info lines does not get them from its workers' terminals either.
    """
    return {
        name: logger.level
        for name, logger in logging.root.manager.loggerDict.items()
        if isinstance(logger, logging.Logger)
        and logger.level != logging.NOTSET
        and not name.startswith(("distributed", "dask", "tornado", "asyncio"))
    }


def _remote_call(
    shipped: bytes, key: str, item: bytes, topic: str, levels: dict[str, int]
) -> _Remote:
    """Runs on a worker: the task, its progress events, its warnings for the client."""
    import cloudpickle
    from distributed import get_worker

    worker = get_worker()
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)

    def report(kind: str, text: str) -> None:
        worker.log_event(topic, {"kind": kind, "key": key, "text": text})

    with _ONE_AT_A_TIME:
        worker_compile_dir()
        report("running", "")
        start = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught, reporting_to(report):
            value, error = _call(cloudpickle.loads(shipped), key, cloudpickle.loads(item))
        seconds = time.perf_counter() - start
    records = [(w.category, str(w.message), w.filename, w.lineno) for w in caught]
    return _Remote(value, error, seconds, worker.address, records)


# ---------------------------------------------------------------------------------------
# one PyTensor compile directory per worker process

#: the compile directory this process claimed (its lock file stays open while it lives)
_CLAIMED: dict[str, Any] = {}


def _claim_slot(root: Path) -> Path:
    """The first ``<root>/<host>-<n>`` no other live process holds (its lock taken)."""
    host = socket.gethostname()
    root.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows: one directory per process id
        return root / f"{host}-pid{os.getpid()}"
    for slot in itertools.count():
        handle = open(root / f"{host}-{slot}.lock", "a")  # noqa: SIM115 - held while alive
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _CLAIMED["lock"] = handle
        return root / f"{host}-{slot}"
    raise AssertionError("unreachable")  # pragma: no cover


def worker_compile_dir() -> Path:
    """Give this process its own PyTensor compile directory; returns it.

    The directory is ``<base_compiledir>/kohpymc-workers/<host>-<n>`` with the smallest
    ``n`` that no other live process on the host holds (a lock file), so a worker's
    cache stays warm across runs and no two live processes share one.  PyTensor fixes
    its compile directory the first time it uses it: when that happened before this call
    the directory stays as it was, and a warning says so.

    Examples
    --------
    >>> worker_compile_dir()  # doctest: +SKIP
    PosixPath('/home/me/.pytensor/kohpymc-workers/node1-0')
    """
    if "dir" in _CLAIMED:
        return _CLAIMED["dir"]
    import pytensor

    target = _claim_slot(Path(pytensor.config.base_compiledir) / "kohpymc-workers")
    try:
        pytensor.config.compiledir = str(target)  # type: ignore[assignment]  # a str is parsed
    except Exception:  # noqa: BLE001 - PyTensor: "can't change ... after initialization"
        if Path(pytensor.config.compiledir) != target:
            warn_user(
                f"PyTensor compiled in this worker process before kohpymc set its compile "
                f"directory; it keeps sharing {pytensor.config.compiledir}",
                RuntimeWarning,
            )
    _CLAIMED["dir"] = Path(pytensor.config.compiledir)
    return _CLAIMED["dir"]


def compile_dir_plugin() -> Any:
    """A Dask worker plugin giving each worker its compile directory before any task.

    :func:`run_tasks` registers it on every cluster it uses (as
    ``"kohpymc-compile-dir"``); it calls :func:`worker_compile_dir` in each worker
    process when the worker starts or when it is registered on a running one.

    Examples
    --------
    >>> plugin = compile_dir_plugin()  # doctest: +SKIP
    >>> client.register_plugin(plugin, name="kohpymc-compile-dir")  # doctest: +SKIP
    """
    from distributed import WorkerPlugin

    class CompileDirPlugin(WorkerPlugin):  # defined here: Dask is imported only when used
        def setup(self, worker: Any) -> None:
            _set_up_worker()

    return CompileDirPlugin()


def _set_up_worker() -> None:
    """The plugin's setup (a module function: the plugin class travels by value)."""
    with _ONE_AT_A_TIME:
        worker_compile_dir()
