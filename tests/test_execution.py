"""Where tasks run: in this process, on a local Dask cluster, on an existing one."""

from __future__ import annotations

import os
import signal
import sys

import pytest

from kohpymc.execution import run_tasks, runs_remotely
from kohpymc.progress import LineDisplay, report_note, report_phase


def _square(key, x):
    report_phase("squaring")
    report_note(f"{key} squared")
    return x * x


def _where_compiled(key, item):
    import pytensor

    return str(pytensor.config.compiledir), os.getpid()


def _dies_or_squares(key, x):
    if x is None:  # a crash in compiled code, or the OS's out-of-memory killer
        os.kill(os.getpid(), signal.SIGKILL)
    return x * x


def test_in_process_runs_in_order_and_reports_failures_and_progress():
    lines = []
    outcomes = list(
        run_tasks(_square, {"a": 2, "b": "x", "c": 3}, progress=LineDisplay(lines.append))
    )
    assert [o.key for o in outcomes] == ["a", "b", "c"]
    assert [o.value for o in outcomes] == [4, None, 9]
    assert outcomes[1].error.startswith("TypeError: can't multiply sequence")
    assert all(o.where == "local" and o.seconds >= 0 for o in outcomes)
    assert lines[0] == "queued: a, b, c"
    assert "[1/3] a: squaring" in lines
    assert "[1/3] a: done in" in lines[3] and lines[3].endswith("(a squared)")
    assert lines[-1].startswith("[3/3] c: done in")


def test_in_process_run_does_not_import_dask():
    """The default path stays light: no Dask in a process that never asked for it."""
    import subprocess

    code = (
        "import sys, kohpymc.execution as e\n"
        "list(e.run_tasks(lambda k, x: x, {'a': 1}))\n"
        "print('distributed' in sys.modules, 'dask' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.stdout.split() == ["False", "False"], done.stderr


def test_workers_start_a_local_cluster_and_close_it_when_abandoned():
    """``workers=2``: a LocalCluster of 2 processes for the run, closed as soon as the caller
    stops reading (an error or Ctrl-C in the caller closes the generator the same way)."""
    from distributed import LocalCluster

    before = set(LocalCluster._instances)
    outcomes = run_tasks(_where_compiled, {f"t{i}": i for i in range(6)}, workers=2)
    first = next(outcomes)
    (cluster,) = [c for c in LocalCluster._instances if c not in before]
    assert len(cluster.workers) == 2 and cluster.status.name == "running"
    assert first.error is None and first.where in cluster.scheduler_info["workers"]
    assert first.value[1] != os.getpid()  # ran in another process
    outcomes.close()
    assert cluster.status.name == "closed"


def test_bad_execution_settings():
    with pytest.raises(ValueError, match="workers must be a positive integer, got 0"):
        next(run_tasks(_square, {"a": 1}, workers=0))
    with pytest.raises(ValueError, match="not both"):
        next(run_tasks(_square, {"a": 1}, workers=2, scheduler="tcp://127.0.0.1:8786"))
    with pytest.raises(ValueError, match="tcp://HOST:PORT"):
        next(run_tasks(_square, {"a": 1}, scheduler="127.0.0.1 8786"))
    assert not runs_remotely(1, None) and runs_remotely(3, None)


def test_unreachable_scheduler_is_a_connection_error():
    import dask

    with (
        dask.config.set({"distributed.comm.timeouts.connect": "2s"}),
        pytest.raises(ConnectionError, match="cannot reach the Dask scheduler 'tcp://127.0.0.1:9'"),
    ):
        next(run_tasks(_square, {"a": 1}, scheduler="tcp://127.0.0.1:9"))


def test_each_worker_process_compiles_in_its_own_directory(dask_cluster):
    import pytensor
    from distributed import Client

    with Client(dask_cluster, set_as_default=False) as client:
        outcomes = list(
            run_tasks(_where_compiled, {f"t{i}": i for i in range(4)}, scheduler=client)
        )
        dirs = {addr: d for addr, (d, _pid) in client.run(_where_compiled, "probe", None).items()}
    root = os.path.join(str(pytensor.config.base_compiledir), "kohpymc-workers")
    assert len(set(dirs.values())) == 2, dirs  # two live workers, two directories
    assert all(d.startswith(root) for d in dirs.values())
    assert str(pytensor.config.compiledir) not in dirs.values()  # not this process's either
    for outcome in outcomes:  # inside each task: the directory of the worker that ran it
        assert outcome.error is None
        assert outcome.value[0] == dirs[outcome.where]


def test_a_dying_worker_fails_its_task_and_the_others_finish(dask_cluster):
    items = {"a": 2, "crash": None, "b": 3, "c": 4}
    lines = []
    outcomes = {
        o.key: o
        for o in run_tasks(
            _dies_or_squares,
            items,
            scheduler=dask_cluster.scheduler_address,
            progress=LineDisplay(lines.append),
        )
    }
    assert set(outcomes) == set(items)
    assert [outcomes[k].value for k in ("a", "b", "c")] == [4, 9, 16]
    assert "worker process died" in outcomes["crash"].error
    assert any(
        line.startswith("[2/4] crash: FAILED: its Dask worker process died") for line in lines
    )


def test_physics_file_loaded_by_path_runs_on_workers(dask_cluster, tmp_path, write_study):
    """A physics function from ``physics.py:model`` lives in a module the workers cannot
    import: it travels by value."""
    from kohpymc import load_study

    spec = load_study(write_study(tmp_path))
    module = spec.physics.function.__module__
    assert module.startswith("kohpymc_user_")
    inputs = {"x": [100.0, 200.0], "P": [2.5, 2.5]}
    here = spec.physics.evaluate(inputs, {"E": 120.0})

    def evaluate(key, params):
        import sys

        return spec.physics.evaluate(inputs, params), module in sys.modules

    address = dask_cluster.scheduler_address
    (outcome,) = run_tasks(evaluate, {"E": {"E": 120.0}}, scheduler=address)
    assert outcome.error is None and outcome.where.startswith("tcp://")
    values, importable_there = outcome.value
    assert not importable_there
    assert list(values) == list(here)


def _level_of_library_logger(key, name):
    import logging

    return logging.getLogger(name).getEffectiveLevel()


def test_workers_log_at_the_levels_set_here(dask_cluster):
    """A command that silenced a library's info lines does not get them from its workers."""
    import logging

    logging.getLogger("kohpymc_test_library").setLevel(logging.ERROR)
    try:
        (outcome,) = run_tasks(
            _level_of_library_logger,
            {"a": "kohpymc_test_library.sub"},
            scheduler=dask_cluster.scheduler_address,
        )
    finally:
        logging.getLogger("kohpymc_test_library").setLevel(logging.NOTSET)
    assert outcome.error is None and outcome.value == logging.ERROR
