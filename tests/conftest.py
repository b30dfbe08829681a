"""Shared fixtures: the beam example, quiet logging, a cache of calibrations."""

from __future__ import annotations

import logging
import warnings

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


@pytest.fixture(scope="session")
def beam_calibrations(beam_physics, beam_data):
    """Calibrate each beam formulation once per session, at the library defaults."""
    from kohpymc import calibrate

    cache: dict[str, object] = {}

    def get(label: str):
        if label not in cache:
            disc = beam.formulations()[label]
            cache[label] = calibrate(beam_physics, beam_data, disc, random_seed=11, warn=False)
        return cache[label]

    return get
