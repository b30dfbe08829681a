"""Fowler–Nordheim injection and Frenkel–Poole emission rates (pure numpy)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from kohpymc.examples.dielectric.constants import _EPS0, _H, _KB, _M0, _Q, THICKNESS, _param


def fowler_nordheim(E: Any, params: Mapping[str, float]) -> np.ndarray:
    """Fowler–Nordheim current density ``A E² exp(-B/E)`` in A/m² (0 for ``E <= 0``).

    Parameters
    ----------
    E : array-like
        Field at the injecting contact, V/m.
    params : mapping
        Needs ``phi_B`` (eV) and ``m_eff`` (m*/m0).

    Examples
    --------
    >>> round(float(fowler_nordheim(1e8, {"phi_B": 1.28, "m_eff": 0.1})), 6)
    0.003127
    """
    phi, mass = _param(params, "phi_B"), _param(params, "m_eff")
    a = _Q**2 / (8.0 * np.pi * _H * phi * mass)
    b = 8.0 * np.pi * np.sqrt(2.0 * mass * _M0) * (_Q * phi) ** 1.5 / (3.0 * _Q * _H)
    E = np.asarray(E, dtype=float)
    Es = np.maximum(E, 1e-6)
    return np.where(E > 0, a * Es**2 * np.exp(-b / Es), 0.0)


def frenkel_poole_rate(V: Any, T: Any, params: Mapping[str, float]) -> np.ndarray:
    """Frenkel–Poole emission rate ``γ / (1 + exp(q(E_A - β√E)/kT))`` in 1/s at ``E = V/d``.

    Parameters
    ----------
    V, T : array-like
        Voltage (V) and temperature (K).
    params : mapping
        Needs ``ln_gamma``, ``E_A`` (eV) and ``eps_inf``.

    Examples
    --------
    >>> p = {"ln_gamma": 16.5, "E_A": 0.95, "eps_inf": 13.0}
    >>> float(frenkel_poole_rate(20.0, 300.0, p)) < float(frenkel_poole_rate(20.0, 360.0, p))
    True
    """
    return np.exp(_log_emission(V, T, params))


def _log_emission(V: Any, T: Any, params: Mapping[str, float]) -> np.ndarray:
    E = np.asarray(V, dtype=float) / THICKNESS
    lowering = np.sqrt(_Q * np.abs(E) / (np.pi * _EPS0 * _param(params, "eps_inf")))
    x = (_param(params, "E_A") - lowering) * _Q / (_KB * np.asarray(T, dtype=float))
    return _param(params, "ln_gamma") - np.logaddexp(0.0, x)
