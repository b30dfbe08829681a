"""Walled log coordinates: kept only where the posterior's real tail stays off the walls.

The model: ``x ~ Uniform(50, 300)`` enters the data as ``100 / x`` next to an offset
``c``, so the posterior of ``ln x`` has a heavy right tail towards the bound 300 (the beam's
modulus under a discrepancy mean, in miniature).  Its profile over ``c`` is closed form:
on the log scale (walls) the density of ``w = ln x`` is ``e^w`` times the likelihood, and
``c`` enters three Gaussian terms with means ``m = (y1 − 100 e^{−w}, y2, 0)``.
"""

import numpy as np
import pymc as pm
import pytest
from scipy import optimize

from kohpymc import reparameterization
from kohpymc.reparameterization import (
    _far_from_walls,
    _wall_drop,
    _whitened,
    find_mode,
    log_coordinates,
    plan,
)
from kohpymc.value_space import value_space

SEED = 1
BOUNDS = (50.0, 300.0)
Y1 = 100.0 / 150.0


def _reciprocal_space(sd):
    """``y1 ~ N(100/x + c, sd/10)``, ``y2 ~ N(c, sd)``, ``c ~ N(0, 1)``: corr(ln x, c) ≈ 0.995."""
    with pm.Model() as model:
        x = pm.Uniform("x", *BOUNDS)
        c = pm.Normal("c", 0.0, 1.0)
        pm.Normal("y1", 100.0 / x + c, sd / 10, observed=[Y1])
        pm.Normal("y2", c, sd, observed=[0.0])
    return value_space(model)


def _profile(w, sd):
    """``max_c log p(w, c)`` (up to a constant) in closed form."""
    m = np.array([Y1 - 100.0 * np.exp(-w), 0.0, 0.0])
    precision = 1.0 / np.array([(sd / 10) ** 2, sd**2, 1.0])
    c = np.sum(m * precision) / np.sum(precision)
    return w - 0.5 * np.sum(precision * (m - c) ** 2)


def _walled_plan(space):
    mode = find_mode(space, seed=SEED)
    return _whitened(space, log_coordinates(space, walls=True), mode.value, mode)


@pytest.mark.parametrize("sd", [0.03, 0.06])
def test_wall_drop_is_the_closed_form_profile(sd):
    """The drop of the log density from the mode to its maximum on each wall, against
    the closed-form profile over c maximised over w by scipy."""
    space = _reciprocal_space(sd)
    walled = _walled_plan(space)
    lower, upper = np.log(BOUNDS)
    best = optimize.minimize_scalar(lambda w: -_profile(w, sd), bounds=(lower, upper))
    for wall in (lower, upper):
        expected = -best.fun - _profile(wall, sd)
        assert _wall_drop(space, walled, 0, wall) == pytest.approx(expected, rel=1e-5)


def test_a_heavy_tail_reaching_a_wall_rules_out_the_walled_coordinates(monkeypatch):
    """sd = 0.06: the bound 300 lies 7.5 Laplace sds of ln x from the mode (the Laplace
    check alone would keep the walls, and the walled map scores best among the Laplace
    maps), but the log density there is only 14.6 below the mode (< 18, a Gaussian's
    drop at 6 sd): the plan samples without walls, bent or not.  sd = 0.03 (drop 60):
    the walled plan is kept."""
    space = _reciprocal_space(0.06)
    walled = _walled_plan(space)
    sd_w = np.sqrt(np.sum(walled.chol**2, axis=1))[0]
    assert (np.log(BOUNDS[1]) - walled.mean[0]) / sd_w > 6.0
    assert not _far_from_walls(space, walled)
    chosen = plan(space, seed=SEED)
    assert not chosen.coordinates.walls, chosen.kind
    monkeypatch.setattr(reparameterization, "_BEND_SCORE", np.inf)  # Laplace maps only
    unbent = plan(space, seed=SEED)
    assert not unbent.coordinates.walls, unbent.kind
    assert unbent.gaussian_score > walled.gaussian_score  # the walls were not outscored

    narrow = _reciprocal_space(0.03)
    assert _far_from_walls(narrow, _walled_plan(narrow))
    assert plan(narrow, seed=SEED).kind == "log-affine"
