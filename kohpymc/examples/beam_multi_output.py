r"""A steel cantilever measured two ways: deflection (μm) and surface strain (με).

A short, deep steel cantilever (its own geometry, not the paper's beam of
:mod:`kohpymc.examples.beam`): length L = 250 mm, width b = 25 mm, depth h = 50 mm
(h/L = 0.2), I = b h³/12, Poisson ratio ν = 0.3, true E = 200 GPa, prior
E ~ Uniform(50, 300) GPa.  A tip load P (kN) is applied; x (mm) runs from the clamp.
The physics model (Euler–Bernoulli) has two outputs:

* deflection ``u`` (μm)::

      u(x) = 1000 · P (3L - x) x² / (6 E I)

* bending strain ``strain`` on the top surface (με, microstrain), from the moment
  ``M(x) = P (L - x)`` at distance ``h/2`` from the neutral axis::

      ε(x) = 10⁶ · P (L - x) h / (2 E I)

(P in kN and E in GPa, so the factors 1000 and 10⁶ convert mm to μm and strain to
με.)  At P = 6 kN the tip deflects 600 μm and the strain at the clamp is 720 με,
below the yield strain of structural steel (≈ 1200–1800 με): a realistic static test.

**Synthetic measurements** (the hidden truth differs from the physics model; each
output has its own discrepancy):

* deflection: Timoshenko's beam (paper Eq. 26) adds shear deformation,
  ``δ_u(x) = 1000 · P (4 + 5ν) h² x / (24 E I)``, linear in x and proportional to P
  (2.75 % of the tip deflection at h/L = 0.2, 16.5 μm at 6 kN); measured by
  displacement sensors with noise sd √0.1 μm (:data:`U_NOISE_SD`, the paper's);
* strain: in a statically determinate cantilever the moment, hence the bending
  strain, is the same in Timoshenko's theory, so the gauges see the Euler–Bernoulli
  strain plus a constant zero offset :data:`STRAIN_OFFSET` = 15 με (the gauges were
  zeroed at another temperature: apparent strain), noise sd :data:`STRAIN_NOISE_SD`
  = 3 με (a foil gauge on a bridge amplifier, static readings).

Calibration at P = 2, 4 and 6 kN (:data:`CALIBRATION_LOADS`), validation at 8 kN.
The matching formulations (:func:`formulations`): for ``u`` an input-dependent
Gaussian (M3) whose mean is linear in ``x``, ``P`` and ``x·P`` (it contains the shear
term ``a·P·x`` exactly, and extrapolates it to a new load); for ``strain`` a constant
bias (M1), the gauge offset.

**Why these positions.** The discrepancy mean of ``u`` takes away every part of the
deflection that is linear in x at each load (its ``P`` and ``x·P`` terms let the line
change with the load).  E changes u through ``∂u/∂E = -u/E ∝ P (3L - x) x²``, which
is itself proportional to P and almost a straight line in x over the outer part of
the beam, so most of it is collinear with the discrepancy mean; only its curvature,
largest near the clamp (where u ≈ 3L x²), tells E apart from the shear term.  Hence
the sensors: one close to the clamp, three around mid-span and one at the tip
(:data:`U_POSITIONS` = 25, 100, 125, 150, 250 mm, the best five of the 25 mm grid for
that curvature).  By the Fisher information (known σ, the discrepancy mean profiled
out, the extra M3 variance ignored) they keep 1.6 % of the information on E that u
carries without a discrepancy: posterior sd of E 0.57 GPa from u alone, against
0.93 GPa (0.5 % kept) for five evenly spaced sensors at x = 50, 100, ..., 250 mm.
A load adds information in proportion to P², but the pattern across loads adds none
(the kept part is ``P`` times a function of x, and the mean's ``P`` and ``x·P`` terms
follow that proportionality); a third load mainly gives M3's variance residual degrees
of freedom: with loads 4 and 6 kN the u-alone posterior of E was heavy-tailed
(kurtosis 4.8, sd 1.45 GPa, 4 × 1000 draws), with 2, 4 and 6 kN it is nearly normal
(kurtosis 0.8).  The strain's E-sensitivity ``∝ P (L - x)`` is a
straight line in x: the constant offset takes its mean level, and 35 % of its
information is left (the slope over the five gauges, :data:`STRAIN_POSITIONS`, and
the change with the load), Fisher sd 0.88 GPa at 3 με.  The two outputs thus carry
information on E of the same order, so calibrating both narrows E against either
alone.

Measured on the shipped data (:func:`posterior_of_E`, i.e.
:func:`~kohpymc.multi_output.calibrate_outputs`; 4 chains × 1000 draws, seed 2026, M3 on
u / M1 on strain): E = 199.90 ± 0.80 GPa from u alone, 198.90 ± 0.86 from the strain
alone, 199.45 ± 0.57 from both (0.71 × the better single sd; the Gaussian combination
``(1/0.80² + 1/0.86²)^(-1/2)`` is 0.59).  Each covers E = 200 (the joint mean is 0.96
joint sds low, a noise deviation: the least-squares estimator with the same nuisance
terms is unbiased over 2000 noise draws).  M0 on both outputs gives 193.9 ± 0.07.
Other noise seeds and the study's reliability table: ``docs/multi-output.md``.
"""

from __future__ import annotations

import argparse
import logging
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.multi_output.data import MultiOutputData
from kohpymc.multi_output.physics import MultiOutputPhysics
from kohpymc.priors import Uniform

__all__ = [
    "LENGTH",
    "WIDTH",
    "HEIGHT",
    "POISSON",
    "INERTIA",
    "TRUE_E",
    "U_NOISE_SD",
    "STRAIN_NOISE_SD",
    "STRAIN_OFFSET",
    "CALIBRATION_LOADS",
    "VALIDATION_LOADS",
    "U_POSITIONS",
    "STRAIN_POSITIONS",
    "TOLERANCE",
    "deflection",
    "shear_deflection",
    "bending_strain",
    "beam_outputs",
    "beam_outputs_jacobian",
    "physics_model",
    "generate_data",
    "data_table",
    "posterior_of_E",
    "formulations",
]

LENGTH = 250.0  # L, mm
WIDTH = 25.0  # b, mm
HEIGHT = 50.0  # h, mm
POISSON = 0.3  # ν
INERTIA = WIDTH * HEIGHT**3 / 12.0  # I, mm⁴
TRUE_E = 200.0  # GPa
#: sd of the deflection noise, μm (the paper's noise variance 0.1 μm²)
U_NOISE_SD = float(np.sqrt(0.1))
#: sd of the strain-gauge noise, με
STRAIN_NOISE_SD = 3.0
#: zero offset of the strain gauges in the synthetic measurements, με
STRAIN_OFFSET = 15.0
#: loads (kN) of the calibration and of the validation data
CALIBRATION_LOADS = (2.0, 4.0, 6.0)
VALIDATION_LOADS = (8.0,)
#: displacement-sensor positions (mm from the clamp): one near the clamp, three at
#: mid-span, one at the tip (they see the curvature of u; see the module docstring)
U_POSITIONS = (25.0, 100.0, 125.0, 150.0, 250.0)
#: strain-gauge positions (mm from the clamp)
STRAIN_POSITIONS = (25.0, 75.0, 125.0, 175.0, 225.0)
#: validation tolerance per output (≈ 2.4 noise sd each): μm, με
TOLERANCE = {"u": 0.75, "strain": 7.5}


def _columns(inputs: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(inputs["x"], dtype=float), np.asarray(inputs["P"], dtype=float)


def deflection(inputs: dict, params: dict) -> np.ndarray:
    """Euler–Bernoulli deflection ``1000 · P (3L - x) x² / (6 E I)`` in μm.

    Examples
    --------
    >>> float(deflection({"x": 250.0, "P": 6.0}, {"E": 200.0}))
    600.0
    """
    x, load = _columns(inputs)
    return 1000.0 * load * (3.0 * LENGTH - x) * x**2 / (6.0 * params["E"] * INERTIA)


def shear_deflection(inputs: dict, E: float = TRUE_E) -> np.ndarray:
    """Timoshenko's shear term ``1000 · P (4 + 5ν) h² x / (24 E I)`` (μm): ``δ_u``.

    Examples
    --------
    >>> round(float(shear_deflection({"x": 250.0, "P": 6.0})), 6)
    16.5
    """
    x, load = _columns(inputs)
    return 1000.0 * load * (4.0 + 5.0 * POISSON) * HEIGHT**2 * x / (24.0 * E * INERTIA)


def bending_strain(inputs: dict, params: dict) -> np.ndarray:
    """Top-surface bending strain ``10⁶ · P (L - x) h / (2 E I)`` in με.

    Examples
    --------
    >>> round(float(bending_strain({"x": 0.0, "P": 6.0}, {"E": 200.0})), 6)
    720.0
    """
    x, load = _columns(inputs)
    return 1e6 * load * (LENGTH - x) * HEIGHT / (2.0 * params["E"] * INERTIA)


def beam_outputs(inputs: dict, params: dict) -> dict[str, np.ndarray]:
    """Both outputs of the Euler–Bernoulli beam: ``{"u": μm, "strain": με}``.

    Examples
    --------
    >>> out = beam_outputs({"x": [250.0], "P": [6.0]}, {"E": 200.0})
    >>> float(out["u"][0]), float(out["strain"][0])
    (600.0, 0.0)
    """
    return {"u": deflection(inputs, params), "strain": bending_strain(inputs, params)}


def beam_outputs_jacobian(inputs: dict, params: dict) -> dict[str, dict[str, np.ndarray]]:
    """``∂G_k/∂E = -G_k / E`` for both outputs.

    Examples
    --------
    >>> float(beam_outputs_jacobian({"x": [250.0], "P": [6.0]}, {"E": 200.0})["u"]["E"][0])
    -3.0
    """
    out = beam_outputs(inputs, params)
    return {k: {"E": -v / params["E"]} for k, v in out.items()}


def physics_model(*, jacobian: bool = True) -> MultiOutputPhysics:
    """Deflection and strain of the Euler–Bernoulli beam, ``E ~ Uniform(50, 300)`` GPa.

    Examples
    --------
    >>> physics_model().outputs
    ('u', 'strain')
    """
    return MultiOutputPhysics(
        beam_outputs,
        {"E": Uniform(50.0, 300.0)},
        inputs=["x", "P"],
        outputs=["u", "strain"],
        jacobian=beam_outputs_jacobian if jacobian else None,
        name="beam_outputs",
    )


def _truth(name: str, inputs: dict, E: float, discrepancy: bool) -> np.ndarray:
    """Noise-free measurement of one output: the physics plus, if asked, its δ."""
    if name == "u":
        return deflection(inputs, {"E": E}) + (shear_deflection(inputs, E) if discrepancy else 0.0)
    return bending_strain(inputs, {"E": E}) + (STRAIN_OFFSET if discrepancy else 0.0)


def generate_data(
    loads: Sequence[float] = CALIBRATION_LOADS,
    *,
    u_positions: Sequence[float] = U_POSITIONS,
    strain_positions: Sequence[float] = STRAIN_POSITIONS,
    seed: int = 0,
    E: float = TRUE_E,
    discrepancy: bool = True,
    noise_sd: dict[str, float] | None = None,
) -> MultiOutputData:
    """Synthetic deflection and strain at every position, load by load.

    Parameters
    ----------
    loads : sequence of float
        Loads P (kN); each is read at all ``u_positions`` and ``strain_positions``.
    u_positions, strain_positions : sequence of float
        Positions x (mm from the clamp) of the displacement sensors and the gauges.
    seed : int
        Seed of the noise (u's noise is drawn first, then the strain's).
    discrepancy : bool
        ``True``: the hidden truth (Timoshenko deflection, offset strain gauges);
        ``False``: the physics model itself (for recovery tests).
    noise_sd : dict, optional
        Noise sd per output; default ``{"u": U_NOISE_SD, "strain": STRAIN_NOISE_SD}``,
        recorded as known.

    Examples
    --------
    >>> data = generate_data(seed=1)
    >>> data.sizes
    {'u': 15, 'strain': 15}
    """
    rng = np.random.default_rng(seed)
    sd = {"u": U_NOISE_SD, "strain": STRAIN_NOISE_SD, **(noise_sd or {})}
    parts = {}
    for name, positions in (("u", u_positions), ("strain", strain_positions)):
        x = np.asarray(positions, dtype=float)
        inputs = {
            "x": np.tile(x, len(loads)),
            "P": np.repeat(np.asarray(loads, dtype=float), x.size),
        }
        y = _truth(name, inputs, E, discrepancy) + rng.normal(0.0, sd[name], size=inputs["x"].size)
        parts[name] = CalibrationData(pd.DataFrame(inputs), y, noise_sd=sd[name], output_name=name)
    return MultiOutputData(parts)


def data_table(data: MultiOutputData, *, decimals: int = 4) -> pd.DataFrame:
    """One row per (P, x) with a column per output, empty where it was not measured.

    The layout of the example's CSV files (``MultiOutputData.from_csv`` reads it back).

    Examples
    --------
    >>> data_table(generate_data(seed=1)).columns.tolist()
    ['x', 'P', 'u', 'strain']
    >>> len(data_table(generate_data(seed=1)))  # 8 positions (two shared) x 3 loads
    24
    """
    frames = [
        pd.DataFrame({**data[k].inputs, k: np.round(data[k].y, decimals)}) for k in data.outputs
    ]
    table = frames[0]
    for frame in frames[1:]:
        table = table.merge(frame, on=["x", "P"], how="outer")
    return table.sort_values(["P", "x"], kind="stable").reset_index(drop=True)


def formulations() -> dict[str, Any]:
    """The matched discrepancies: M3 with mean in ``x, P, x·P`` for ``u``, M1 for ``strain``.

    Examples
    --------
    >>> sorted(formulations())
    ['strain', 'u']
    """
    from kohpymc.discrepancy import ConstantBias, InputDependentGaussian

    return {"u": InputDependentGaussian(mean=["x", "P", "x*P"]), "strain": ConstantBias()}


def posterior_of_E(
    data: MultiOutputData, chosen: dict[str, Any], **options: Any
) -> dict[str, tuple[float, float]]:
    """Mean and sd of E from u alone, the strain alone and both (``calibrate_outputs``).

    ``chosen`` maps each output to its formulation (``None``: M0); ``options`` go to
    :func:`~kohpymc.multi_output.calibrate_outputs`.

    Examples
    --------
    >>> posterior_of_E(generate_data(seed=1), formulations(), draws=300)  # doctest: +SKIP
    {'u': (199.8, 1.0), 'strain': (199.9, 1.1), 'u+strain': (199.9, 0.75)}
    """
    from kohpymc.multi_output.calibration import calibrate_outputs

    physics, result = physics_model(), {}
    for outputs in (["u"], ["strain"], ["u", "strain"]):
        cal = calibrate_outputs(
            physics, data.select(outputs), {k: chosen[k] for k in outputs}, **options
        )
        E = cal.posterior["E"].values.ravel()
        result["+".join(outputs)] = (float(E.mean()), float(E.std()))
    return result


def _main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Beam with deflection and strain outputs.")
    parser.add_argument("--draws", type=int, default=1000)
    parser.add_argument("--tune", type=int, default=1000)
    parser.add_argument("--chains", type=int, default=4)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args(argv)
    logging.getLogger("pymc").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message="PyTensor could not link to a BLAS")
    options = {"draws": args.draws, "tune": args.tune, "chains": args.chains, "warn": False}
    scenarios = {
        "exact data, M0": (False, dict.fromkeys(("u", "strain"))),
        "Timoshenko u + gauge offset, M3 (u) / M1 (strain)": (True, formulations()),
    }
    print(f"true E = {TRUE_E:g} GPa")
    for title, (hidden, chosen) in scenarios.items():
        data = generate_data(seed=args.seed, discrepancy=hidden)
        rows = posterior_of_E(data, chosen, random_seed=args.seed, **options)
        sds = [rows["u"][1], rows["strain"][1]]
        print(f"\n{title}")
        for key, (mean, sd) in rows.items():
            print(f"  {key:10s} E mean {mean:8.2f}  sd {sd:6.3f}")
        print(f"  Gaussian combination of the two sds: {sum(s**-2 for s in sds) ** -0.5:.3f}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(_main())
