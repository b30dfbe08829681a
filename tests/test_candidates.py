"""Candidate discrepancy terms shaped like physics, from a model's inputs."""

from __future__ import annotations

import numpy as np
import pytest

from kohpymc.candidates import candidate_library, design_matrix, monomial_name


def test_monomials_of_up_to_three_inputs_with_positive_only_negative_powers():
    data = {"t": np.linspace(0, 2, 11), "m": np.linspace(1, 8, 11), "H": np.linspace(30, 70, 11)}
    terms = {t.name: t for t in candidate_library(data)}
    assert {"t^3/m", "t^4", "sqrt(m)", "1/m^2", "t*m*H", "t^2*sqrt(m)/H"} <= set(terms)
    assert not any(n.startswith(("1/t", "sqrt(t)")) or "/t" in n for n in terms)  # t hits 0
    np.testing.assert_allclose(terms["t^3/m"](data), data["t"] ** 3 / data["m"])
    assert terms["t^3/m"].inputs == ("t", "m")
    # 3 inputs, t with 4 exponents, m and H with 8: 20 + 96 + 256 monomials
    assert sum(t.kind == "monomial" for t in terms.values()) == 20 + (32 + 32 + 64) + 256


def test_shapes_with_a_scale_and_shifted_powers():
    data = {"T": np.linspace(290.0, 330.0, 9), "x": np.linspace(0.0, 4.0, 9)}
    terms = {t.name: t for t in candidate_library(data, exponents=(1,))}
    assert "(T-310)^2" in terms  # far from 0: shifted to its median
    assert not any(n.startswith("(x-") for n in terms)
    kinds = {t.kind for t in terms.values() if t.shape is not None}
    assert kinds == {"saturation", "threshold", "decay"}
    thr = next(t for t in terms.values() if t.kind == "threshold" and t.inputs == ("x",))
    np.testing.assert_allclose(thr.with_scale(1.5)(data), np.maximum(0.0, data["x"] - 1.5))
    assert thr.with_scale(1.5).name == "max(0,x-1.5)"
    ref = candidate_library(data, exponents=(1,), references={"x": 2.0}, shapes=())
    assert "(x-2)^2" in {t.name for t in ref}


def test_names():
    assert monomial_name({"t": 3, "m": -1}) == "t^3/m"
    assert monomial_name({"x": 0.5, "P": -0.5}) == "sqrt(x)/sqrt(P)"
    assert monomial_name({"m": -1, "L": -2}) == "1/(m*L^2)"


def test_user_terms_and_errors():
    data = {"x": np.array([-1.0, 0.0, 1.0])}
    terms = candidate_library(data, extra={"1/x": (["x"], lambda d: 1.0 / d["x"])})
    with pytest.raises(ValueError, match=r"'1/x' is not finite at 1 row"):
        design_matrix(terms, data)
    with pytest.raises(ValueError, match="empty"):
        candidate_library({"x": np.ones(4)})
    with pytest.raises(KeyError, match="not in the data"):
        candidate_library(data, ["y"])
    with pytest.raises(ValueError, match="duplicate"):
        candidate_library(data, extra={"x": (["x"], lambda d: d["x"])})
    with pytest.raises(ValueError, match="0 is not an exponent"):
        candidate_library(data, exponents=(0, 1))
