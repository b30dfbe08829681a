"""Nutpie's chains in forked processes: the exact posterior, errors and when threads stay."""

import json
import multiprocessing

import arviz as az
import numpy as np
import pytest
import xarray as xr

import kohpymc as kp
from kohpymc.chain_processes import chain_groups, sample_chains, why_not_processes
from kohpymc.priors import Uniform

SEED = 20261127


def _line(seed: int = SEED):
    """y = a·x with known noise sd 0.4 and a flat prior on a: N(â, σ²/Σx²) is exact."""
    x = np.linspace(0.1, 2.0, 15)
    y = 3.0 * x + np.random.default_rng(seed).normal(0.0, 0.4, x.size)
    data = kp.CalibrationData({"x": x}, y, noise_sd=0.4)
    physics = kp.PhysicsModel(
        lambda inputs, p: p["a"] * inputs["x"], {"a": Uniform(-100.0, 100.0)}, inputs=["x"]
    )
    mean = float(x @ y / (x @ x))
    return physics, data, mean, 0.4 / float(np.sqrt(x @ x))


def test_numpy_physics_posterior_is_exact_and_the_same_on_one_or_two_cores():
    """A numpy physics function (a Python Op, nutpie's Python callback): with 2 cores the
    4 chains run in 2 forked processes, with one in turn here; the draws are identical
    (each chain sampled alone with its own seed), match the conjugate posterior (mean
    within 0.1 sd, sd within 10 %), and every chain has its own draws and sample stats."""
    physics, data, mean, sd = _line()
    runs = {
        cores: kp.calibrate(
            physics, data, None, draws=500, tune=500, chains=4, cores=cores, random_seed=SEED
        )
        for cores in (1, 2)
    }
    for cores, cal in runs.items():
        sampling = json.loads(cal.idata.attrs["sampling"])
        assert sampling["nutpie_backend"].startswith("python")
        assert sampling["chain_processes"] == ("2" if cores == 2 else "1 (one core)")
    one, two = (runs[c].idata for c in (1, 2))
    np.testing.assert_array_equal(one.posterior["a"].values, two.posterior["a"].values)
    np.testing.assert_array_equal(
        one.sample_stats["diverging"].values, two.sample_stats["diverging"].values
    )
    a = two.posterior["a"]
    assert a.sizes == {"chain": 4, "draw": 500}
    assert two.posterior["chain"].values.tolist() == [0, 1, 2, 3]
    assert len({round(float(v), 12) for v in a.isel(draw=0).values}) == 4  # own seeds
    assert abs(float(a.mean()) - mean) < 0.1 * sd
    assert float(a.std()) == pytest.approx(sd, rel=0.1)
    assert float(az.rhat(two)["a"]) < 1.01


def _one_chain(seed, progress):
    x = np.random.default_rng(seed).normal(size=(1, 4))
    posterior = xr.Dataset({"x": (("chain", "draw"), x)})
    return az.InferenceData(posterior=posterior), [f"failure with seed {seed}"]


def test_chains_are_joined_in_order_with_their_failures_wherever_they_ran():
    """3 chains on 2 cores: groups of 2 and 1, joined as chains 0-2 with every chain's
    failure; the same draws in turn on one core."""
    idata, failures, ran = sample_chains(_one_chain, chains=3, cores=2, seed=1)
    assert ran == "2"
    assert idata.posterior.sizes == {"chain": 3, "draw": 4}
    assert idata.posterior["chain"].values.tolist() == [0, 1, 2]
    assert len(failures) == 3 and len(set(failures)) == 3
    alone, again, ran = sample_chains(_one_chain, chains=3, cores=1, seed=1)
    assert ran == "1 (one core)" and again == failures
    np.testing.assert_array_equal(idata.posterior["x"].values, alone.posterior["x"].values)


def _raising(seed, progress):
    raise ValueError("bad physics in a sampling process")


def test_an_error_in_a_sampling_process_is_raised_here():
    with pytest.raises(ValueError, match="bad physics in a sampling process") as info:
        sample_chains(_raising, chains=4, cores=2, seed=1)
    assert any("in the sampling process" in note for note in info.value.__notes__)


def _why_not_in_daemon(sender):
    sender.send(why_not_processes(4, 2))


def test_threads_stay_in_a_daemonic_process_and_on_one_core():
    """A Dask worker's process is daemonic and may not start processes."""
    receiver, sender = multiprocessing.get_context("fork").Pipe(duplex=False)
    process = multiprocessing.get_context("fork").Process(
        target=_why_not_in_daemon, args=(sender,), daemon=True
    )
    process.start()
    reason = receiver.recv()
    process.join()
    assert "daemonic" in reason
    assert why_not_processes(4, 1) == "one core"
    assert why_not_processes(1, 2) == "one chain"
    assert why_not_processes(4, 2) == ""
    assert chain_groups(5, 2) == [3, 2]
