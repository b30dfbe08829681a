r"""The cantilever beam with two outputs: tip-loaded deflection and surface strain.

The beam of :mod:`kohpymc.examples.beam` (L = h = 400 μm, b = 1 μm, ν = 0.3, load
scale c, true E = 200 GPa) measured two ways at positions x along it (x = 0 at the
clamp):

* deflection ``u`` (μm), Euler–Bernoulli (the physics model, paper Eq. 25)::

      u(x) = c · P (3L - x) x² / (6 E I)

* bending strain ``strain`` on the top surface (dimensionless, raw: 1e-3 ... 5e-2),
  from the moment ``M(x) = c · P (L - x)`` at distance ``h/2`` from the neutral axis::

      ε(x) = M(x) (h / 2) / (E I) = c · P (L - x) h / (2 E I)

Both outputs depend on the one parameter E, through ``1/E``; they differ by three
orders of magnitude in size.

**Synthetic measurements** (the hidden truth differs from the physics model):

* deflection: Timoshenko (paper Eq. 26), which adds shear deformation, so
  ``δ_u(x) = c · P (4 + 5ν) h² x / (24 E I)``, linear in x (paper Eq. 27);
* strain: the bending strain of a statically determinate cantilever is the same in
  Timoshenko's theory (shear changes the deflection, not the moment), so the strain
  gauges see the Euler–Bernoulli strain plus a constant zero offset of the gauges,
  ``δ_ε = STRAIN_OFFSET`` (a gauge zero drift the model does not have).

Noise: deflection sd √0.1 μm (as in the paper), strain sd :data:`STRAIN_NOISE_SD`.
The matching formulations are a linear-mean discrepancy for ``u`` and a constant bias
for ``strain`` (:func:`formulations`).

Run ``python -m kohpymc.examples.beam_multi_output`` to calibrate E from u alone, from
the strain alone and from both, and print the posterior of E and the reliability table.
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
from kohpymc.examples.beam import (
    HEIGHT,
    INERTIA,
    LENGTH,
    LOAD_SCALE,
    NOISE_VAR,
    TRUE_E,
    euler_bernoulli,
    timoshenko,
)
from kohpymc.multi_output.data import MultiOutputData
from kohpymc.multi_output.physics import MultiOutputPhysics
from kohpymc.priors import Uniform

__all__ = [
    "STRAIN_NOISE_SD",
    "STRAIN_OFFSET",
    "beam_outputs",
    "beam_outputs_jacobian",
    "bending_strain",
    "physics_model",
    "generate_data",
    "formulations",
]

#: sd of the strain measurement noise (raw strain; the strain itself is up to ~0.05)
STRAIN_NOISE_SD = 1e-3
#: constant zero offset of the strain gauges in the synthetic measurements
STRAIN_OFFSET = 1e-3


def bending_strain(inputs: dict, params: dict) -> np.ndarray:
    """Surface bending strain ``c · P (L - x) h / (2 E I)`` (dimensionless).

    Examples
    --------
    >>> round(float(bending_strain({"x": 0.0, "P": 2.5}, {"E": 200.0})), 6)
    0.045
    """
    x = np.asarray(inputs["x"], dtype=float)
    load = np.asarray(inputs["P"], dtype=float)
    return LOAD_SCALE * load * (LENGTH - x) * HEIGHT / (2.0 * params["E"] * INERTIA)


def beam_outputs(inputs: dict, params: dict) -> dict[str, np.ndarray]:
    """Both outputs of the Euler–Bernoulli beam: ``{"u": μm, "strain": raw}``.

    Examples
    --------
    >>> out = beam_outputs({"x": [400.0], "P": [2.5]}, {"E": 200.0})
    >>> float(out["u"][0]), float(out["strain"][0])
    (12.0, 0.0)
    """
    return {"u": euler_bernoulli(inputs, params), "strain": bending_strain(inputs, params)}


def beam_outputs_jacobian(inputs: dict, params: dict) -> dict[str, dict[str, np.ndarray]]:
    """``∂G_k/∂E = -G_k / E`` for both outputs.

    Examples
    --------
    >>> float(beam_outputs_jacobian({"x": [400.0], "P": [2.5]}, {"E": 200.0})["u"]["E"][0])
    -0.06
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


def generate_data(
    loads: Sequence[float] = (2.5,),
    *,
    n_points: int = 20,
    seed: int = 0,
    E: float = TRUE_E,
    discrepancy: bool = True,
    noise_sd: dict[str, float] | None = None,
) -> MultiOutputData:
    """Synthetic deflection and strain at ``n_points`` positions per load.

    Parameters
    ----------
    loads : sequence of float
        Loads P; each gets positions ``x = L/n, 2L/n, ..., L`` for u and ``x = 0,
        L/n, ..., L (n - 1)/n`` for the strain (a gauge at the free end reads zero).
    discrepancy : bool
        ``True``: the hidden truth (Timoshenko deflection, offset strain gauges);
        ``False``: the physics model itself (for recovery tests).
    noise_sd : dict, optional
        Noise sd per output; default ``{"u": √0.1, "strain": STRAIN_NOISE_SD}``,
        recorded as known.

    Examples
    --------
    >>> data = generate_data((2.5, 3.0), seed=1)
    >>> data.sizes
    {'u': 40, 'strain': 40}
    """
    rng = np.random.default_rng(seed)
    sd = {"u": float(np.sqrt(NOISE_VAR)), "strain": STRAIN_NOISE_SD, **(noise_sd or {})}
    step = LENGTH / n_points
    x_u = np.linspace(step, LENGTH, n_points)
    x_s = np.linspace(0.0, LENGTH - step, n_points)
    parts = {}
    for name, x in (("u", x_u), ("strain", x_s)):
        xs = np.concatenate([x for _ in loads])
        ps = np.concatenate([np.full(n_points, float(p)) for p in loads])
        inputs = {"x": xs, "P": ps}
        if name == "u":
            truth = timoshenko(inputs, E) if discrepancy else euler_bernoulli(inputs, {"E": E})
        else:
            truth = bending_strain(inputs, {"E": E}) + (STRAIN_OFFSET if discrepancy else 0.0)
        y = truth + rng.normal(0.0, sd[name], size=xs.size)
        parts[name] = CalibrationData(pd.DataFrame(inputs), y, noise_sd=sd[name], output_name=name)
    return MultiOutputData(parts)


def formulations() -> dict[str, Any]:
    """Per-output discrepancy: linear mean in x for ``u``, constant bias for ``strain``.

    Examples
    --------
    >>> sorted(formulations())
    ['strain', 'u']
    """
    from kohpymc.discrepancy import ConstantBias, InputDependentGaussian

    return {"u": InputDependentGaussian(mean=["x"]), "strain": ConstantBias()}


def _main(argv: Sequence[str] | None = None) -> int:
    from kohpymc.multi_output.calibration import calibrate_outputs
    from kohpymc.multi_output.reliability import reliability_table

    parser = argparse.ArgumentParser(description="Beam with deflection and strain outputs.")
    parser.add_argument("--draws", type=int, default=1000)
    parser.add_argument("--tune", type=int, default=1000)
    parser.add_argument("--chains", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args(argv)
    logging.getLogger("pymc").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message="PyTensor could not link to a BLAS")

    physics = physics_model()
    scenarios = {
        "exact data, M0": (False, dict.fromkeys(("u", "strain"))),
        "Timoshenko u + gauge offset, M3 (u) / M1 (strain)": (True, formulations()),
    }
    print(f"true E = {TRUE_E:g} GPa")
    for title, (hidden, chosen) in scenarios.items():
        calibration = generate_data((2.5, 3.0), seed=args.seed, discrepancy=hidden)
        validation = generate_data((3.5,), seed=args.seed + 1, discrepancy=hidden)
        rows = []
        for outputs in (["u"], ["strain"], ["u", "strain"]):
            cal = calibrate_outputs(
                physics,
                calibration.select(outputs),
                {k: chosen[k] for k in outputs},
                draws=args.draws,
                tune=args.tune,
                chains=args.chains,
                random_seed=args.seed,
                warn=False,
            )
            E = cal.posterior["E"].values.ravel()
            rows.append({"outputs": "+".join(outputs), "E mean": E.mean(), "E sd": E.std()})
        table = reliability_table(
            cal, validation, tolerance={"u": 0.75, "strain": 1e-3}, random_seed=args.seed
        )
        print(f"\n{title}")
        print(pd.DataFrame(rows).set_index("outputs").round(2).to_string())
        print(table.round(3).to_string())
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(_main())
