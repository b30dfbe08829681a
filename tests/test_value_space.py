"""kohpymc.value_space: the expand map in its own compile mode gives the same values."""

from __future__ import annotations

import numpy as np
import pymc as pm
import pytensor

from kohpymc.value_space import _expand_mode, value_space


def _model() -> pm.Model:
    with pm.Model() as model:
        a = pm.Uniform("a", 50.0, 300.0)
        s = pm.HalfNormal("s", 1.0)
        pm.Deterministic("ratio", a / (1.0 + s))
        pm.Normal("y", a / 100.0, s, observed=[1.0, 1.5, 2.0])
    return model


def test_expand_of_a_numba_space_matches_the_c_backend():
    model = _model()
    numba, c = value_space(model, mode="NUMBA"), value_space(model, mode="FAST_RUN")
    x = np.array([0.3, -0.2])
    for name, value in numba.expand(x).items():
        np.testing.assert_allclose(value, c.expand(x)[name], rtol=1e-12)
    np.testing.assert_allclose(numba.logp_dlogp(x)[0], c.logp_dlogp(x)[0], rtol=1e-12)


def test_expand_mode_is_c_for_numba_only_with_a_compiler():
    assert _expand_mode("NUMBA") == ("FAST_RUN" if pytensor.config.cxx else "NUMBA")
    assert _expand_mode(None) is None
