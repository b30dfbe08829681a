"""kohpymc.batched_map: a graph of one vector run for many rows at once, against scipy per row."""

from __future__ import annotations

import numpy as np
import pytensor.tensor as pt
import scipy.linalg as sla

from kohpymc import PhysicsModel, Uniform
from kohpymc.batched_map import rows_function


def _spd(x):
    """A 3 × 3 positive definite matrix built from the vector ``x`` (length 3)."""
    f = pt.stack([[x[0], 0.0, 0.0], [x[1], 1.0, 0.0], [x[2], x[0], 2.0]])
    return f @ f.T + pt.eye(3)


def _spd_numpy(x):
    f = np.array([[x[0], 0.0, 0.0], [x[1], 1.0, 0.0], [x[2], x[0], 2.0]])
    return f @ f.T + np.eye(3)


def test_linear_algebra_sums_and_clip_match_scipy_row_by_row():
    """Cholesky (lower, upper), cho_solve, triangular solves (lower, upper, unit diagonal,
    matrix right-hand side), a three-term sum and a clip, for 200 random rows."""
    x = pt.vector("x")
    a = _spd(x)
    b = pt.stack([x[0], x[1] - x[2], 1.0])
    low = pt.linalg.cholesky(a, lower=True)
    up = pt.linalg.cholesky(a, lower=False)
    outputs = [
        low,
        up,
        pt.linalg.cho_solve((low, True), b),
        pt.linalg.solve_triangular(a, b, lower=True),
        pt.linalg.solve_triangular(a, b, lower=False, unit_diagonal=True),
        pt.linalg.solve_triangular(a, pt.outer(b, b) + pt.eye(3), lower=True),
        x[0] + pt.exp(x[1]) + x[2] * x[0],
        pt.clip(x, -0.5, 0.7),
        pt.constant(np.arange(3.0)),  # does not depend on x: repeated per row
    ]
    f = rows_function(x, outputs)
    assert f is not None
    rows = np.random.default_rng(3).normal(size=(200, 3))
    got = f(rows)
    for r, row in enumerate(rows):
        am = _spd_numpy(row)
        bm = np.array([row[0], row[1] - row[2], 1.0])
        unit = np.tril(am, -1) + np.triu(am)  # upper solve reads the upper triangle only
        np.fill_diagonal(unit, 1.0)
        expected = [
            sla.cholesky(am, lower=True),
            sla.cholesky(am, lower=False),
            sla.cho_solve((sla.cholesky(am, lower=True), True), bm),
            sla.solve_triangular(am, bm, lower=True),
            np.linalg.solve(np.triu(unit), bm),
            sla.solve_triangular(am, np.outer(bm, bm) + np.eye(3), lower=True),
            row[0] + np.exp(row[1]) + row[2] * row[0],
            np.clip(row, -0.5, 0.7),
            np.arange(3.0),
        ]
        for value, want in zip(got, expected, strict=True):
            np.testing.assert_allclose(value[r], want, rtol=1e-10, atol=1e-12)


def test_a_python_op_is_left_to_the_compiled_map():
    """A numpy physics Op would run once per row in Python: no batched map."""
    decay = PhysicsModel(
        lambda x, p: p["a"] * np.exp(-x["t"]), {"a": Uniform(1.0, 2.0)}, inputs=["t"]
    )
    theta = pt.vector("theta")
    assert rows_function(theta, [decay.tensor(theta, pt.as_tensor(np.array([[0.0]])))]) is None


def test_a_non_positive_definite_matrix_gives_nan_in_its_row_only():
    x = pt.vector("x")
    f = rows_function(x, [pt.linalg.cholesky(pt.stack([[x[0], 0.0], [0.0, x[1]]]))])
    assert f is not None
    out = f(np.array([[1.0, 4.0], [1.0, -4.0]]))[0]
    np.testing.assert_allclose(out[0], np.diag([1.0, 2.0]))
    assert np.isnan(out[1]).all()


def test_a_graph_with_many_shape_nodes_is_left_to_the_compiled_map():
    """Vectorising ``Shape`` nodes re-infers shapes each time (a GridGP expand map with 25 of
    them took 598 s): such a graph gets None, the compiled per-draw path; none is fine."""
    import pytensor.tensor as pt

    from kohpymc.batched_map import rows_function

    x = pt.vector("x")
    many = sum(pt.cast(pt.arange(k + 1).shape[0], "float64") * x[0] for k in range(6))
    plain = pt.exp(x[0]) * x[1]
    assert rows_function(x, [many]) is None
    assert rows_function(x, [plain]) is not None
