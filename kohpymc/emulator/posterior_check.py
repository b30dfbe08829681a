"""The emulator scored where a formulation's posterior lies: one simulator run per formulation.

The checks before sampling (:func:`~kohpymc.emulator.checking.check_at_data`) look at
the parameters that fit the data best without a discrepancy.  A formulation with a
discrepancy can put its posterior elsewhere: on a damped oscillator with friction
missing, the posterior of ζ under a GP discrepancy lay 18 of M0's sds from M0's, where the
default emulator (100 runs, 348 after refinement) erred by 0.73 noise sds, and that
posterior was 2.6 of the direct calibration's sds off, with nothing to say so.
:func:`check_at_posterior` runs the simulator once at the posterior mean of θ on the
calibration rows and scores the emulator there.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from kohpymc.data import CalibrationData
from kohpymc.emulator.at_data import SINGLE, EmulatorsAtData, SimulatorFailedAt
from kohpymc.emulator.checking import (
    MAX_NOISE_SHIFT,
    EmulatorCheck,
    coverage_bounds,
    noise_sd_shift,
)

__all__ = ["MAX_POSTERIOR_SHIFT", "check_at_posterior"]

#: largest bias of a posterior mean that an emulator's error may cause, in that
#: posterior's sds (linearised; the issue's own tolerance for an emulated calibration)
MAX_POSTERIOR_SHIFT = 0.25


def check_at_posterior(
    emulator: Any,
    data: CalibrationData,
    mean: Mapping[str, float],
    sd: Mapping[str, float],
    *,
    label: str = "the posterior",
    cache: str | Path | None = None,
    level: float = 0.9,
    max_shift: float = MAX_POSTERIOR_SHIFT,
    workers: int = 1,
    scheduler: Any = None,
) -> EmulatorCheck:
    """Score an emulator at a posterior mean of θ against one simulator run there.

    The simulator runs once at ``mean`` on the calibration rows (cached in ``cache``
    like the design's runs), and the emulator is scored there.  Problems:

    - the coverage of its ``level`` bands below what ``level`` allows
      (:func:`~kohpymc.emulator.checking.coverage_bounds`): its error is larger than
      its own variance says, so the likelihood's ``Σ_η`` does not cover it;
    - its error ``r = simulator - emulator mean`` biasing θ by more than ``max_shift``
      of the posterior's sds, linearised: the least-squares θ through the emulator lies
      about ``(JᵀJ)⁻¹Jᵀr`` from the simulator's (``J`` the emulator mean's Jacobian at
      ``mean``), taken over ``sd``.  This leaves the discrepancy out, and it
      underestimates the bias under one: on the oscillator above, the GP formulation's
      predicted bias of ζ was -0.44 of its sds, the measured one (against the direct
      calibration) -1.7;
    - without a known noise sd, the emulator's variance and error moving the noise sd's
      best fit by more than :data:`~kohpymc.emulator.checking.MAX_NOISE_SHIFT` of its sds
      (:func:`~kohpymc.emulator.checking.noise_sd_shift` on the residuals at ``mean``;
      an 8-run oscillator emulator refined to 876 runs: predicted σ 0.108 → 0.052, -5.2
      sds, sampled σ_obs -4.6 of the direct posterior's sds).

    Parameters
    ----------
    emulator : Emulator
        The emulator (its ``physics`` is the simulator).
    data : CalibrationData
        The calibration data.
    mean, sd : mapping of str to float
        The posterior mean and sd of every physics parameter.
    label : str
        Names the posterior in the problems (e.g. ``"M4's posterior"``).
    cache : path, optional
        Cache folder of the simulator runs.
    level : float
        Nominal coverage of the bands.
    max_shift : float
        Largest allowed linearised bias, in posterior sds.
    workers, scheduler :
        Where the simulator run goes (:func:`kohpymc.run_tasks`).

    Returns
    -------
    EmulatorCheck
        ``kind = "at the mean of <label>"``; ``point`` the mean, ``shift`` the
        linearised bias in posterior sds; a simulator failure at the mean is a problem.

    Examples
    --------
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> check = check_at_posterior(emulate(physics, data, runs=30), data,
    ...                            {"E": 200.0}, {"E": 5.0})
    >>> check.kind, check.fit
    ('at the mean of the posterior', True)
    """
    target = EmulatorsAtData.of(emulator, data)
    theta = {k: float(mean[k]) for k in target.parameters}
    kind = f"at the mean of {label}"
    try:
        simulated = target.simulated_at(theta, cache=cache, workers=workers, scheduler=scheduler)
    except SimulatorFailedAt as err:
        empty = np.empty(0)
        failed = (
            f"the simulator failed at the mean of {label} ({_format(theta)}) on {err.where} "
            f"(first: {err.first}): the emulator there rests on no run"
        )
        return EmulatorCheck(kind, empty, empty, empty, level, problems=[failed], point=theta)
    predicted, variance = target.predicted_at(SINGLE, theta)
    check = EmulatorCheck(kind, simulated[SINGLE], predicted, np.sqrt(variance), level, point=theta)
    check.shift = _posterior_shift(target, check, sd)
    check.problems += _problems(check, label, max_shift)
    check.problems += _noise_problems(target, check, label)
    return check


def _posterior_shift(
    target: EmulatorsAtData, check: EmulatorCheck, sd: Mapping[str, float]
) -> dict[str, float]:
    """Parameter -> the linearised bias of θ the emulator's error causes, in ``sd``."""
    J, _, _ = target.linearised(SINGLE, check.point)
    move, *_ = np.linalg.lstsq(J, check.simulated - check.mean, rcond=None)
    return {
        k: float(m / sd[k]) if sd[k] > 0 else 0.0
        for k, m in zip(target.parameters, move, strict=True)
    }


def _problems(check: EmulatorCheck, label: str, max_shift: float) -> list[str]:
    """The check's problems: bands that miss, and a bias beyond ``max_shift``."""
    where = f"at the mean of {label} ({_format(check.point)})"
    problems = []
    low, _ = coverage_bounds(check.level, check.simulated.size)
    if check.coverage < low:
        problems.append(
            f"{where} its {check.level:.0%} bands cover {check.coverage:.2f} of the "
            f"simulator's outputs at the calibration rows (< {low:.2f})"
        )
    moved = {k: v for k, v in (check.shift or {}).items() if abs(v) > max_shift}
    if moved:
        named = ", ".join(f"{k} {v:+.2g}" for k, v in moved.items())
        problems.append(
            f"{where} its error (rms {check.rmse:.3g}) biases {named} of that posterior's "
            f"sds (linearised, without the discrepancy: likely more; > {max_shift})"
        )
    return problems


def _noise_problems(target: EmulatorsAtData, check: EmulatorCheck, label: str) -> list[str]:
    """An unknown noise sd's best fit moved by the emulator (:func:`noise_sd_shift`), if any.

    The residuals of simulator and emulator at the posterior mean, the emulator's
    covariance on the rows; with a discrepancy the residual holds it too (both sides),
    so the comparison says how the emulator alone moves the noise's fit.
    """
    data = target.data[SINGLE]
    if data.noise_sd is not None:
        return []
    y = np.asarray(data.y, float)
    _, _, covariance = target.linearised(SINGLE, check.point)
    simulated, emulated, move = noise_sd_shift(y - check.simulated, y - check.mean, covariance)
    check.noise_shift = float(move)
    if abs(move) <= MAX_NOISE_SHIFT:
        return []
    return [
        f"at the mean of {label} ({_format(check.point)}) its variance and error move the "
        f"unknown noise sd's best fit from {simulated:.3g} (the simulator's) to "
        f"{emulated:.3g}, {move:+.2g} of its sds (> {MAX_NOISE_SHIFT})"
    ]


def _format(theta: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in theta.items())
