"""The slow-simulator example: real sleeps, real LocalCluster, simulator calls counted.

Every simulator call appends a line (pid and θ) to a log file, so calls made in Dask
worker processes are counted here without trusting the library's own bookkeeping.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import arviz as az
import numpy as np
import pandas as pd
import pytest

from kohpymc.cli import main
from kohpymc.config import load_study
from kohpymc.examples import slow_simulator as example

SLEEP = 0.05  # seconds per simulator call in these tests (the example's default is 1 s)


def _calls(log: Path) -> list[tuple[int, float, float]]:
    """The logged calls: (pid, alpha, Ts) per line."""
    if not log.exists():
        return []
    return [
        (int(p), float(a), float(t))
        for p, a, t in (ln.split() for ln in log.read_text().split("\n") if ln)
    ]


@pytest.mark.parametrize(
    ("name", "times", "seed"),
    [
        ("calibration", example.CALIBRATION_TIMES, 2026),
        ("validation", example.VALIDATION_TIMES, 2027),
    ],
)
def test_data_files_are_generate_data(name, times, seed):
    frame = pd.read_csv(example.STUDY_FILE.parent / "data" / f"slow_simulator_{name}.csv")
    data = example.generate_data(times, seed=seed)
    np.testing.assert_array_equal(frame["t"].to_numpy(), data.inputs["t"])
    np.testing.assert_array_equal(frame["T_back"].to_numpy(), data.y)


def test_the_simulator_sleeps_once_per_call_and_logs_it(tmp_path, monkeypatch):
    log = tmp_path / "calls.log"
    t = np.array(example.CALIBRATION_TIMES)
    begin = time.perf_counter()
    out = example.slab_temperature({"t": t}, {"alpha": 4.2, "Ts": 100.0}, seconds=0.2, log=log)
    assert time.perf_counter() - begin >= 0.2  # one sleep for all 20 times
    np.testing.assert_allclose(out, example.back_face_temperature(t, 4.2, 100.0))
    assert _calls(log) == [(os.getpid(), 4.2, 100.0)]
    # the environment sets the default sleep and log (as Dask workers inherit them)
    monkeypatch.setenv("KOHPYMC_SLOW_SIMULATOR_SECONDS", "0")
    monkeypatch.setenv("KOHPYMC_SLOW_SIMULATOR_LOG", str(log))
    example.slab_temperature({"t": t}, {"alpha": 2.0, "Ts": 80.0})
    assert len(_calls(log)) == 2
    with pytest.raises(ValueError, match="seconds must be >= 0"):
        example.slab_temperature({"t": t}, {"alpha": 2.0, "Ts": 80.0}, seconds=-1)
    # the series: T_0 at t = 0, T_s for t → ∞, monotone between
    values = example.back_face_temperature([0.0, 5.0, 20.0, 1e5], 4.2, 100.0)
    assert values[0] == example.INITIAL_C and abs(values[-1] - 100.0) < 1e-9
    assert np.all(np.diff(values) > 0)


def test_emulator_runs_on_a_local_cluster_call_the_simulator_once_each_and_cache(
    tmp_path, dask_cluster
):
    """Design runs on a real 2-worker LocalCluster: one sleeping call per run, in the
    workers; a second emulate() over the same cache calls the simulator zero times."""
    from kohpymc.emulator import emulate

    log = tmp_path / "calls.log"
    spec = load_study(example.write_study(tmp_path, seconds=SLEEP, log=log))
    address = dask_cluster.scheduler_address
    cache = tmp_path / "runs"
    em = emulate(spec.physics, spec.calibration, runs=24, cache=cache, scheduler=address)
    here = os.getpid()
    # load_study runs the physics once on each data set at the prior centre, in this process
    assert {(a, t) for pid, a, t in _calls(log) if pid == here} == {(5.5, 100.0)}
    runs = [c for c in _calls(log) if c[0] != here]  # the calls in the worker processes
    assert len(runs) == 24 == em.runs.simulated == em.n_runs
    assert len({(a, t) for _, a, t in runs}) == 24  # one call per θ of the design
    before = len(_calls(log))
    again = emulate(spec.physics, spec.calibration, runs=24, cache=cache, scheduler=address)
    assert len(_calls(log)) == before and again.runs.simulated == 0 and again.runs.cached == 24
    np.testing.assert_allclose(again.hyper.lengthscales, em.hyper.lengthscales)


@pytest.mark.slow
def test_emulated_study_on_a_local_cluster_covers_the_truth_and_reruns_from_cache(
    tmp_path, capsys, dask_cluster
):
    """The shipped study (150 runs, M0 and M1; 2 × 500 draws here) with a 0.05 s simulator
    on the 2-worker LocalCluster: every θ simulated once, in the workers (the 150 design
    runs, the refinement rounds' runs and each check's run at the best fit), a posterior
    that covers the truth, and a rerun that runs the simulator nowhere."""
    log = tmp_path / "calls.log"
    path = example.write_study(
        tmp_path, seconds=SLEEP, log=log, sampling={"draws": 500, "tune": 500}
    )
    out = tmp_path / "out"
    args = ["study", str(path), "--out", str(out), "--no-figures", "--quiet"]
    address = dask_cluster.scheduler_address
    assert main([*args, "--scheduler", address]) == 0
    capsys.readouterr()
    calls = _calls(log)
    here = os.getpid()
    runs = [(a, t) for pid, a, t in calls if pid != here]
    table = pd.read_csv(out / "emulator" / "runs.csv")
    refined = json.loads((out / "emulator" / "refine_at_data.json").read_text())
    assert len(table) == 150 + refined["added_runs"]
    fits = {(r["check"]["point"]["alpha"], r["check"]["point"]["Ts"]) for r in refined["rounds"]}
    assert len(runs) == len(set(runs))  # no θ simulated twice
    assert set(runs) == set(zip(table["alpha"], table["Ts"], strict=True)) | fits
    # the only calls in this process: the pre-flight check that each formulation builds
    # (compose_model evaluates the physics at the prior centre)
    assert {(a, t) for pid, a, t in calls if pid == here} <= {(5.5, 100.0)}
    post = az.from_netcdf(out / "M0.nc").posterior
    for name, truth in (("alpha", example.TRUE_ALPHA), ("Ts", example.TRUE_TS)):
        low, high = np.quantile(post[name].values, [0.005, 0.995])
        assert low < truth < high, (name, low, high)
        assert float(post[name].std()) < {"alpha": 0.3, "Ts": 1.0}[name]
    before = len(calls)
    assert main([*args[:-1], "--scheduler", address]) == 0  # not --quiet: reuse is printed
    printed = capsys.readouterr().out
    assert "M0: reused" in printed and "M1: reused" in printed
    after = _calls(log)[before:]
    assert [c for c in after if c[0] != here] == []  # no simulator run: all cached
    assert {(a, t) for _, a, t in after} <= {(5.5, 100.0)}  # the pre-flight calls only
