"""Shared fixtures: the beam example, quiet logging, a cache of calibrations."""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import pytest

from kohpymc.examples import beam

#: seed of the beam calibration data used across tests
BEAM_SEED = 2026


@pytest.fixture(autouse=True, scope="session")
def _quiet():
    logging.getLogger("pymc").setLevel(logging.ERROR)
    logging.getLogger("pytensor.tensor.blas").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message="PyTensor could not link to a BLAS")
    yield


@pytest.fixture(scope="session")
def beam_physics():
    return beam.physics_model()


@pytest.fixture(scope="session")
def beam_data():
    return beam.generate_data((2.5,), seed=BEAM_SEED)


@pytest.fixture(scope="session")
def beam_validation():
    return beam.generate_data((3.5,), seed=BEAM_SEED + 1)


def _prior_calibration(physics, data, formulation, draws=12, seed=0):
    """A Calibration whose "posterior" is a few prior draws (no sampling): for contract tests
    of prediction and pointwise log-likelihoods on any formulation."""
    import arviz as az
    import pymc as pm

    from kohpymc import Calibration
    from kohpymc.model import compose_model

    built = compose_model(physics, data, formulation)
    model = built.model
    names = [v.name for v in model.free_RVs + model.deterministics]  # not "y": it may not draw
    with model:
        prior = pm.sample_prior_predictive(draws=draws, var_names=names, random_seed=seed)
    posterior = prior.prior
    if "chain" not in posterior.dims:  # pragma: no cover - PyMC always adds it
        posterior = posterior.expand_dims(chain=[0])
    idata = az.InferenceData(posterior=posterior)
    return Calibration(physics, data, formulation, built, idata)


@pytest.fixture(scope="session")
def prior_calibration():
    """``prior_calibration(physics, data, formulation, draws=12, seed=0)``: see above."""
    return _prior_calibration


@pytest.fixture(scope="session")
def beam_calibrations(beam_physics, beam_data):
    """Calibrate each beam formulation once per session, at the library defaults."""
    from kohpymc import calibrate

    cache: dict[str, object] = {}

    def get(label: str):
        if label not in cache:
            disc = beam.formulations()[label]
            # cores=2: the same draws as sequential chains (PyMC seeds each chain), half the wait
            cache[label] = calibrate(
                beam_physics, beam_data, disc, random_seed=11, cores=2, warn=False
            )
        return cache[label]

    return get


PHYSICS = """
import numpy as np

def model(inputs, params):
    x = np.asarray(inputs["x"])
    if np.any(x > 400.0):
        raise ValueError("x beyond the beam length 400")
    return 240.0 * inputs["P"] * (1200.0 - x) * x**2 / (6 * params["E"] * 400.0**3 / 12)
"""


def _write_study(folder: Path, toml: str | None = None, **replace: str) -> Path:
    """A beam study in ``folder``: physics.py, calib.csv, valid.csv, study.toml."""
    (folder / "physics.py").write_text(PHYSICS)
    cal = beam.generate_data((2.5,), n_points=8, seed=1)
    val = beam.generate_data((3.5,), n_points=6, seed=2)
    for name, d in (("calib.csv", cal), ("valid.csv", val)):
        rows = ["x,P,u"] + [
            f"{float(x)!r},{float(p)!r},{float(y)!r}"
            for x, p, y in zip(d.inputs["x"], d.inputs["P"], d.y, strict=True)
        ]
        (folder / name).write_text("\n".join(rows) + "\n")
    text = toml or STUDY
    for old, new in replace.items():
        text = text.replace(old, new)
    path = folder / "study.toml"
    path.write_text(text)
    return path


STUDY = """
[physics]
function = "physics.py:model"
inputs = ["x", "P"]
output = "u"
[physics.parameters]
E = { prior = "uniform", lower = 50, upper = 300 }
[data]
calibration = "calib.csv"
validation = "valid.csv"
noise_sd = 0.316
[validation]
tolerance = 0.75
[formulations]
M0 = "none"
M3 = { type = "input_dependent", mean = ["x"], log_variance = ["x"] }
M4 = { type = "gp", inputs = ["x"], mean = ["x", "P", "x*P"] }
[sampling]
draws = 100
tune = 100
chains = 2
seed = 4
"""


@pytest.fixture
def write_study():
    """``write_study(folder, toml=None, **replace)``: a small beam study TOML + CSVs +
    physics file in ``folder`` (``replace`` edits the TOML text); returns its path."""
    return _write_study


@pytest.fixture(scope="session")
def dask_cluster():
    """A real ``dask.distributed.LocalCluster`` of 2 single-threaded worker processes, shared
    by every test that needs an existing cluster (starting one costs seconds). Configured as
    the README recommends for ``dask scheduler``: a task whose worker dies fails at once."""
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        cluster = LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
            silence_logs=logging.CRITICAL,
        )  # fmt: skip
    yield cluster
    cluster.close()
