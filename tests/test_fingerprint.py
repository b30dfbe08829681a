"""Fingerprints: equal for equal inputs (across processes too), different for any change."""

from __future__ import annotations

import subprocess
import sys

from kohpymc import CalibrationData, ConstantBias, Normal, PhysicsModel, Uniform
from kohpymc.config import load_study
from kohpymc.fingerprint import data_fingerprint, formulation_fingerprint, physics_fingerprint


def _line(inputs, params):
    return params["a"] * inputs["x"]


def test_a_change_in_prior_data_or_formulation_changes_its_fingerprint():
    base = PhysicsModel(_line, {"a": Uniform(0.0, 2.0)}, ["x"])
    assert physics_fingerprint(base) == physics_fingerprint(
        PhysicsModel(_line, {"a": Uniform(0.0, 2.0)}, ["x"])
    )
    # a change in the 8th significant digit of a prior bound is a change
    assert physics_fingerprint(base) != physics_fingerprint(
        PhysicsModel(_line, {"a": Uniform(0.0, 2.0000001)}, ["x"])
    )
    data = CalibrationData({"x": [1.0, 2.0]}, [0.5, 1.0])
    assert data_fingerprint(data) != data_fingerprint(
        CalibrationData({"x": [1.0, 2.0]}, [0.5, 1.0], noise_sd=0.1)
    )
    assert data_fingerprint(data) != data_fingerprint(CalibrationData({"z": [1.0, 2.0]}, data.y))
    assert formulation_fingerprint(ConstantBias()) != formulation_fingerprint(
        ConstantBias(prior=Normal(0.0, 2.0))
    )


def test_a_physics_file_has_the_same_fingerprint_in_another_process(tmp_path, write_study):
    """A function loaded from a file gets a per-process module name; the fingerprint must
    not depend on it (else a rerun never reuses anything)."""
    path = write_study(tmp_path)
    here = physics_fingerprint(load_study(path).physics)
    code = (
        "from kohpymc.config import load_study; from kohpymc.fingerprint import "
        f"physics_fingerprint; print(physics_fingerprint(load_study({str(path)!r}).physics))"
    )
    there = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert there == here
    (tmp_path / "physics.py").write_text((tmp_path / "physics.py").read_text() + "\n# edited\n")
    assert physics_fingerprint(load_study(path).physics) != here
