"""Candidate discrepancy terms from a model's inputs."""

from __future__ import annotations

import numpy as np
import pytest

from kohpymc.candidates import candidate_library, design_matrix


def test_library_contents_and_inputs():
    data = {"t": np.linspace(0, 100, 11), "V": np.repeat([10.0, 20.0], [5, 6]), "k": np.ones(11)}
    terms = {t.name: t for t in candidate_library(data)}
    assert "k" not in terms and not any("k" in t.inputs for t in terms.values())  # constant
    assert {"t", "t^2", "t^3", "V", "V*t"} - set(terms) == {"V*t"} and "t*V" in terms
    assert "log(t)" not in terms and "log(V)" in terms  # t includes 0
    exps = [n for n in terms if n.startswith("exp(-t/")]
    assert exps == ["exp(-t/5)", "exp(-t/10)", "exp(-t/20)", "exp(-t/40)", "exp(-t/80)"]
    np.testing.assert_allclose(terms["exp(-t/20)"](data), np.exp(-data["t"] / 20.0))
    assert terms["t*V"].inputs == ("t", "V")
    assert terms["t*V"].expression == "c * t * V"


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
