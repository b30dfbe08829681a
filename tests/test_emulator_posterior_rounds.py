"""Runs added at the posteriors where the emulator is unfit (kohpymc.emulator.posterior_rounds)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import xarray as xr

import kohpymc as kp
from kohpymc.emulator import emulate
from kohpymc.emulator.posterior_check import check_at_posterior
from kohpymc.emulator.posterior_rounds import PosteriorRounds, refine_at_posteriors

_NOISE = 0.02


def _decay(inputs, params):
    return params["A"] * np.exp(-params["k"] * np.asarray(inputs["t"], float))


def _setup():
    physics = kp.PhysicsModel(
        _decay, {"A": kp.Uniform(0.5, 2.0), "k": kp.Uniform(0.1, 3.0)}, inputs=["t"],
        name="decay",
    )  # fmt: skip
    t = np.linspace(0.0, 3.0, 30)
    y = _decay({"t": t}, {"A": 1.2, "k": 2.0}) + np.random.default_rng(5).normal(0, _NOISE, 30)
    data = kp.CalibrationData(pd.DataFrame({"t": t}), y, noise_sd=_NOISE)
    validation = kp.CalibrationData(pd.DataFrame({"t": [3.5, 4.0]}), [0.001, 0.0004])
    return physics, data, validation


def _posterior(mean, sd, n=400, seed=2):
    """A Gaussian stand-in for a formulation's posterior (4 chains)."""
    rng = np.random.default_rng(seed)
    return xr.Dataset(
        {k: (("chain", "draw"), rng.normal(m, sd[k], (4, n // 4))) for k, m in mean.items()}
    )


def test_runs_at_a_posterior_outside_the_design_make_the_emulator_fit_there(tmp_path):
    """The design covers k ∈ [0.1, 1] and a posterior sits at k = 2 (where the data put
    it): the check there fails (bias of tens of sds).  One round at that posterior's
    mean and 2p + 1 = 5 of its draws, on the calibration and validation rows, and the
    check there passes, its error 100× smaller; every θ ran once, cached."""
    physics, data, validation = _setup()
    em = emulate(physics, data, runs=40, seed=1, bounds={"k": (0.1, 1.0)})
    mean, sd = {"A": 1.2, "k": 2.0}, {"A": 0.02, "k": 0.04}
    before = check_at_posterior(em, data, mean, sd)
    assert not before.fit
    refined, thetas = refine_at_posteriors(
        em, data, {"M4": _posterior(mean, sd)}, validation=validation, new_runs=10,
        cache=tmp_path,
    )  # fmt: skip
    assert len(thetas) == 6 and set(thetas["posterior"]) == {"M4"}
    np.testing.assert_allclose(thetas.loc[0, ["A", "k"]].to_numpy(float), [1.2, 2.0], atol=0.01)
    assert refined.n_runs == em.n_runs + 6 * (data.n + validation.n)
    after = check_at_posterior(refined, data, mean, sd)
    assert after.fit, after.problems
    assert after.rmse < before.rmse / 100
    # the validation rows ran at each θ too: predictions there rest on runs
    _, var = refined.predict(validation.inputs, mean)
    _, var_before = em.predict(validation.inputs, mean)
    assert np.all(np.sqrt(var) < np.sqrt(var_before) / 10)
    assert len(list(tmp_path.iterdir())) == 6 * (data.n + validation.n)


def test_the_record_is_this_studys_only_and_written_whole(tmp_path):
    record = PosteriorRounds("key-a", [{"unfit": {"M4": ["off"]}, "runs_added": 10}])
    record.write(tmp_path)
    assert PosteriorRounds.read(tmp_path, "key-a").done == 1
    assert PosteriorRounds.read(tmp_path, "key-b").done == 0  # another study's settings
    (tmp_path / "refine_at_posterior.json").write_text("{not json")
    assert PosteriorRounds.read(tmp_path, "key-a").done == 0  # unreadable: rounds run again
    assert [p.name for p in tmp_path.iterdir()] == ["refine_at_posterior.json"]
