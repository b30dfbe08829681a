"""The emulator: designs, cached simulator runs, the GP, its checks, its likelihood."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from kohpymc import PhysicsModel, Uniform
from kohpymc.emulator import (
    design_box,
    extend_design,
    maximin_distance,
    run_design,
    space_filling_design,
)
from kohpymc.examples import beam

# ----------------------------------------------------------------------------- design


def test_designs_stay_in_the_box_and_are_latin():
    box = {"x": (0.0, 2.0), "a": (-1.0, 1.0), "b": (10.0, 20.0)}
    for method in ("maximin-lhs", "lhs", "sobol"):
        d = space_filling_design(box, 16, method=method, seed=3)
        assert list(d.columns) == ["x", "a", "b"] and len(d) == 16
        for k, (lo, hi) in box.items():
            assert d[k].between(lo, hi).all(), (method, k)
    d = space_filling_design(box, 16, method="maximin-lhs", seed=3)
    for k, (lo, hi) in box.items():  # one point per stratum in every column
        strata = np.floor((d[k].to_numpy() - lo) / (hi - lo) * 16).astype(int)
        assert sorted(strata) == list(range(16))


def test_maximin_lhs_spreads_points_better_than_plain_lhs():
    box = {"x": (0.0, 1.0), "a": (0.0, 1.0), "b": (0.0, 1.0)}
    plain = [
        maximin_distance(space_filling_design(box, 30, method="lhs", seed=s).to_numpy())
        for s in range(5)
    ]
    best = [maximin_distance(space_filling_design(box, 30, seed=s).to_numpy()) for s in range(5)]
    assert min(best) > max(plain)


def test_design_box_uses_data_ranges_and_prior_box():
    data = beam.generate_data(seed=1)
    box = design_box(beam.physics_model(), data)
    assert box["x"] == (float(data.inputs["x"].min()), float(data.inputs["x"].max()))
    assert box["E"] == (50.0, 300.0)
    with pytest.raises(KeyError, match="'x'"):
        design_box(beam.physics_model())


def test_extended_design_keeps_old_points_and_adds_far_ones():
    box = {"x": (0.0, 1.0), "a": (0.0, 1.0)}
    first = space_filling_design(box, 10, seed=1)
    more = extend_design(first, box, 5, seed=2)
    assert len(more) == 15
    pd.testing.assert_frame_equal(more.iloc[:10], first)
    new = more.iloc[10:].to_numpy()
    gaps = np.min(np.linalg.norm(new[:, None] - first.to_numpy()[None], axis=-1), axis=1)
    assert gaps.min() > 0.05


# ----------------------------------------------------------------------------- runs


class _Counted:
    """A simulator that counts its calls and fails where a < 0.1."""

    def __init__(self):
        self.calls = 0
        self.rows = 0

    def __call__(self, inputs, params):
        self.calls += 1
        self.rows += len(inputs["x"])
        if params["a"] < 0.1:
            raise RuntimeError("solver diverged")
        return params["a"] * np.sin(3 * inputs["x"]) + params["b"] * inputs["x"]


def _counted_physics():
    counter = _Counted()
    physics = PhysicsModel(
        counter, {"a": Uniform(0.0, 2.0), "b": Uniform(-1.0, 1.0)}, inputs=["x"], name="counted"
    )
    return counter, physics


def test_cached_runs_are_not_repeated_and_an_extension_runs_only_new_points(tmp_path):
    counter, physics = _counted_physics()
    box = {"x": (0.0, 1.0), "a": (0.2, 2.0), "b": (-1.0, 1.0)}
    design = space_filling_design(box, 12, seed=4)
    first = run_design(physics, design, cache=tmp_path)
    assert first.simulated == 12 and counter.rows == 12 and len(first.points) == 12
    again = run_design(physics, design, cache=tmp_path)
    assert counter.rows == 12 and again.simulated == 0 and again.cached == 12
    pd.testing.assert_frame_equal(first.points, again.points)
    bigger = extend_design(design, box, 5, seed=5)
    more = run_design(physics, bigger, cache=tmp_path)
    assert counter.rows == 17 and more.simulated == 5 and more.cached == 12
    assert len(list(tmp_path.glob("*.json"))) == 17
    assert not list(tmp_path.glob(".*"))  # no temporary files left


def test_runs_sharing_theta_go_to_one_simulator_call():
    counter, physics = _counted_physics()
    design = pd.DataFrame(
        {"x": [0.1, 0.5, 0.9, 0.3], "a": [1.0, 1.0, 1.0, 0.5], "b": [0.2, 0.2, 0.2, 0.0]}
    )
    runs = run_design(physics, design)
    assert counter.calls == 2 and counter.rows == 4
    expected = design["a"] * np.sin(3 * design["x"]) + design["b"] * design["x"]
    np.testing.assert_allclose(runs.y, expected)


def test_failed_runs_are_recorded_and_skipped(tmp_path):
    counter, physics = _counted_physics()
    design = pd.DataFrame({"x": [0.1, 0.5, 0.9], "a": [1.0, 0.05, 1.5], "b": [0.2, 0.0, -0.3]})
    runs = run_design(physics, design, cache=tmp_path)
    assert len(runs.points) == 2 and len(runs.failed) == 1
    assert runs.failed["a"].tolist() == [0.05]
    assert "solver diverged" in runs.failed["error"].iloc[0]
    calls = counter.calls
    again = run_design(physics, design, cache=tmp_path)  # the failure is cached too
    assert counter.calls == calls and len(again.failed) == 1
    run_design(physics, design, cache=tmp_path, retry_failed=True)
    assert counter.calls == calls + 1


def test_a_design_missing_a_column_is_named():
    _, physics = _counted_physics()
    with pytest.raises(KeyError, match=r"\['b'\]"):
        run_design(physics, pd.DataFrame({"x": [0.1], "a": [1.0]}))
