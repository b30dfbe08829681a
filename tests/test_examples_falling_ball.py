"""The falling-ball real-data example: data copy, split, pooled noise, physics, study file.

Reference values are computed independently here (the CSV read with the ``csv`` module,
replicate groups and pooled variances by hand with numpy).  No sampling.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from kohpymc import check_formulation
from kohpymc.config import load_study
from kohpymc.discrepancy import (
    ConstantBias,
    GaussianProcess,
    IIDGaussian,
    InputDependentGaussian,
    NoDiscrepancy,
)
from kohpymc.examples import falling_ball as fb

EXAMPLES = Path(fb.__file__).parent
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "falling_ball.csv"
STUDY = EXAMPLES / "falling_ball_study.toml"


def _read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return (
        np.array([float(r["height_m"]) for r in rows]),
        np.array([float(r["time_s"]) for r in rows]),
    )


def _pooled_sd_by_hand(h: np.ndarray, t: np.ndarray) -> float:
    ss, dof = 0.0, 0
    for value in np.unique(h):
        group = t[h == value]
        ss += float(np.sum((group - group.mean()) ** 2))
        dof += group.size - 1
    return float(np.sqrt(ss / dof))


@pytest.fixture(scope="module")
def data():
    return fb.load_data()


@pytest.fixture(scope="module")
def split(data):
    return fb.split_at_gap(data)


# ------------------------------------------------------------------------------ data
def test_shipped_copy_identical_to_the_shared_file():
    if not SHARED.is_file():
        pytest.skip(f"{SHARED} not present (fresh clone)")
    assert fb.DATA_FILE.read_bytes() == SHARED.read_bytes()


def test_shipped_copy_has_21_heights_with_3_replicates(data):
    h, t = _read(fb.DATA_FILE)
    assert h.size == 63
    heights, counts = np.unique(h, return_counts=True)
    assert heights.size == 21 and np.all(counts == 3)
    np.testing.assert_array_equal(data.inputs["height_m"], h)
    np.testing.assert_array_equal(data.y, t)
    assert data.input_names == ("height_m",) and data.output_name == "time_s"
    # the gap between 1.958 m and 2.670 m is the largest spacing in the design
    steps = np.diff(heights)
    assert tuple(heights[np.argmax(steps) + np.array([0, 1])]) == fb.GAP


def test_split_at_gap(data, split):
    cal, val = split
    h = data.inputs["height_m"]
    hc, hv = cal.inputs["height_m"], val.inputs["height_m"]
    assert np.all(hc < 2.0) and np.all(hv > 2.6)
    assert set(h[h < 2.0]) == set(hc) and set(h[h > 2.6]) == set(hv)
    assert not set(hc) & set(hv)
    assert cal.n + val.n == data.n == 63 and (cal.n, val.n) == (33, 30)
    # union = all rows, each exactly once (compare sorted (height, time) pairs)
    both = sorted(zip(np.r_[hc, hv], np.r_[cal.y, val.y], strict=True))
    assert both == sorted(zip(h, data.y, strict=True))


def test_pooled_replicate_sd_by_hand(data, split):
    h, t = _read(fb.DATA_FILE)
    assert data.noise_sd_estimated
    assert data.noise_sd == pytest.approx(_pooled_sd_by_hand(h, t), rel=1e-12)
    # Eq. 28 with n1 = 21 settings and n2 = 3 replicates
    means = {v: t[h == v].mean() for v in np.unique(h)}
    ss = sum((ti - means[hi]) ** 2 for hi, ti in zip(h, t, strict=True))
    assert data.noise_sd == pytest.approx(np.sqrt(ss / (21 * (3 - 1))), rel=1e-12)
    # each part is pooled over its own replicates only
    cal, val = split
    below = h < fb.SPLIT_HEIGHT
    assert cal.noise_sd == pytest.approx(_pooled_sd_by_hand(h[below], t[below]), rel=1e-12)
    assert val.noise_sd == pytest.approx(_pooled_sd_by_hand(h[~below], t[~below]), rel=1e-12)
    assert cal.noise_sd < data.noise_sd < val.noise_sd


# --------------------------------------------------------------------------- physics
def test_drag_free_time_and_jacobian_against_finite_differences():
    h = np.array([0.178, 1.0, 2.67, 4.272])
    np.testing.assert_allclose(
        fb.drag_free_time({"height_m": h}, {"g": 9.81}), np.sqrt(h / 4.905), rtol=1e-14
    )
    for g in (5.5, 9.81, 14.0):
        step = 1e-5 * g
        fd = (
            fb.drag_free_time({"height_m": h}, {"g": g + step})
            - fb.drag_free_time({"height_m": h}, {"g": g - step})
        ) / (2 * step)
        jac = fb.drag_free_time_jacobian({"height_m": h}, {"g": g})["g"]
        np.testing.assert_allclose(jac, fd, rtol=1e-8)
    physics = fb.physics_model()
    assert physics.parameter_names == ("g",) and physics.inputs == ("height_m",)
    prior = physics.parameters["g"]
    assert (prior.kind, prior.args["lower"], prior.args["upper"]) == ("uniform", 5.0, 15.0)


def test_drag_free_model_underpredicts_above_the_gap(data):
    h, t = data.inputs["height_m"], data.y
    resid = t - np.sqrt(2 * h / fb.G_REFERENCE)
    above = resid[h > 2.6]
    se = above.std(ddof=1) / np.sqrt(above.size)
    assert above.mean() > 3 * se
    # per-height means: the top three heights all take longer than drag-free fall
    top = np.unique(h)[-3:]
    assert all(resid[h == v].mean() > 0.1 for v in top)
    # and the signal is much weaker below the gap, where the model is calibrated
    below = resid[h < 2.0]
    assert abs(below.mean()) < above.mean() / 3


def test_formulations_identifiable_at_the_prior_centre(split):
    cal, _ = split
    forms = fb.formulations()
    assert list(forms) == ["M0", "M1", "M2", "M3", "M4"]
    for label, disc in forms.items():
        report = check_formulation(fb.physics_model(), cal, disc)
        assert report.identifiable, label


def test_tolerance_is_justified_by_the_data(data, split):
    _, val = split
    assert 1.0 < fb.TOLERANCE / data.noise_sd < 3.0
    assert 0.05 < fb.TOLERANCE / val.y.mean() < 0.15


# --------------------------------------------------------------------- study file
def test_shipped_study_loads_and_equals_the_split(split):
    spec = load_study(STUDY)
    for got, want in zip((spec.calibration, spec.validation), split, strict=True):
        np.testing.assert_array_equal(got.inputs["height_m"], want.inputs["height_m"])
        np.testing.assert_array_equal(got.y, want.y)
        np.testing.assert_array_equal(got.replicates, want.replicates)
        assert got.noise_sd == pytest.approx(want.noise_sd, rel=1e-14)
        assert got.noise_sd_estimated
    assert spec.tolerance == fb.TOLERANCE
    assert spec.physics.parameter_names == ("g",)
    prior = spec.physics.parameters["g"]
    assert (prior.args["lower"], prior.args["upper"]) == fb.G_PRIOR_RANGE
    assert spec.physics.jacobian is fb.drag_free_time_jacobian
    kinds = {k: type(v) for k, v in spec.formulations.items()}
    assert kinds == {
        "M0": NoDiscrepancy,
        "M1": ConstantBias,
        "M2": IIDGaussian,
        "M3": InputDependentGaussian,
        "M4": GaussianProcess,
    }
    assert kinds == {k: type(v) for k, v in fb.formulations().items()}
    assert spec.formulations["M3"].mean.terms == ("1", "height_m")
    assert spec.formulations["M3"].log_variance.terms == ("1", "height_m")
    assert spec.formulations["M4"].mean.terms == ("1", "height_m")
    assert spec.sampling["random_seed"] == 2026


def test_split_csvs_are_the_rows_of_the_shipped_copy():
    h, t = _read(fb.DATA_FILE)
    hc, tc = _read(EXAMPLES / "data" / "falling_ball_calibration.csv")
    hv, tv = _read(EXAMPLES / "data" / "falling_ball_validation.csv")
    below = h < fb.SPLIT_HEIGHT
    np.testing.assert_array_equal(hc, h[below])
    np.testing.assert_array_equal(tc, t[below])
    np.testing.assert_array_equal(hv, h[~below])
    np.testing.assert_array_equal(tv, t[~below])
