"""Units, physical constants, the Table 3 prior box, the truth and the design settings."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy import constants

_Q = constants.e  # C
_H = constants.h  # J s
_M0 = constants.m_e  # kg
_EPS0 = constants.epsilon_0  # F/m
_KB = constants.k  # J/K

THICKNESS = 200e-9  # d, m (200 nm Si3N4)
EPS_R = 7.5  # static relative permittivity of Si3N4
MOBILITY = 1e-7  # μ, m²/(V s): hopping drift mobility (sets v_d = μ V/d)
THERMAL_VELOCITY = 1e5  # v_th, m/s
CURRENT_UNIT = 1e5  # A/m² -> nA/cm²
#: field drop at the injecting contact per trapped electron density (centroid d/2), V m²
_FEEDBACK = _Q * THICKNESS / (2.0 * _EPS0 * EPS_R)

#: Table 3 of the paper: uniform prior ranges of the seven physical parameters
PRIOR_RANGES: dict[str, tuple[float, float]] = {
    "ln_NT": (55.3, 61.5),
    "phi_B": (0.8, 1.4),
    "ln_sigma": (-55.3, -50.6),
    "ln_gamma": (16.1, 25.3),
    "eps_inf": (0.1, 15.0),
    "m_eff": (0.01, 1.0),
    "E_A": (0.01, 1.0),
}
#: parameters of the hidden truth (inside the priors)
TRUE_PARAMS: dict[str, float] = {
    "ln_NT": 56.0,
    "phi_B": 1.28,
    "ln_sigma": -52.0,
    "ln_gamma": 16.5,
    "eps_inf": 13.0,
    "m_eff": 0.1,
    "E_A": 0.95,
}
VOLTAGES = (20.0, 25.0, 30.0)  # V
TEMPERATURES = (300.0, 330.0, 360.0, 390.0)  # K
T_END = 100.0  # s, end of the measured transient
NOISE_SD = 0.3  # nA/cm², measurement-noise sd (one value for all settings)
DELTA_EPS = 3.0  # Δε, dipolar relaxation strength of the truth
TAU_300 = 30.0  # s, Debye time at 300 K
E_POL = 0.155  # eV, activation energy of the Debye time


def _param(params: Mapping[str, Any], name: str) -> Any:
    """A parameter as a float, or as an array for per-setting parameter values."""
    try:
        value = params[name]
    except KeyError:
        raise KeyError(f"dielectric model: missing parameter {name!r}") from None
    return value if isinstance(value, np.ndarray) else float(value)
