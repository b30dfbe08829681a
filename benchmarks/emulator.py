"""The GP emulator against the direct model: accuracy, bands, posterior agreement, time.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.emulator [--out benchmarks/results] [--quick]

Problem (the test model of ``tests/test_emulator.py``): ``G = a exp(-k x)``,
``a ~ U(0.5, 3)``, ``k ~ U(0.2, 2)``, 20 points on ``x ∈ [0, 3]``, noise sd 0.05 known,
truth a = 1.7, k = 0.8.  Emulators over (x, a, k) on maximin Latin hypercubes.

1. Emulator accuracy: held-out coverage of the 90 % bands and RMSE / sd on 200 Sobol runs,
   and leave-one-out, per kernel (Matérn 5/2, SE) and number of runs.
2. Posteriors (M0, nutpie, 2 × 1000 draws, seed 1): direct PyTensor model vs the emulator,
   full vs diagonal emulator covariance; the differences of the posterior means in direct
   posterior sds, the sd ratios, wall times.

Tables go to the terminal and to ``<out>/emulator.md``.  The dielectric stand-in is not
here: its 480 rows per θ call for an emulator of the whole curve (a principal-component
basis, issue 18 item 6), and a pointwise 10-input GP on ≤ 300 runs with a 480 × 480
emulator covariance per gradient is too slow for NUTS.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytensor.tensor as pt  # noqa: E402

import kohpymc as kp  # noqa: E402
from kohpymc.emulator import (  # noqa: E402
    Emulator,
    check_emulator,
    design_box,
    run_design,
    space_filling_design,
)
from kohpymc.study_files import markdown_table  # noqa: E402

PRIORS = {"a": kp.Uniform(0.5, 3.0), "k": kp.Uniform(0.2, 2.0)}
TRUTH = {"a": 1.7, "k": 0.8}
NOISE = 0.05
SAMPLING = {"draws": 1000, "tune": 1000, "chains": 2, "random_seed": 1, "warn": False}


def decay(inputs, params):
    return params["a"] * np.exp(-params["k"] * inputs["x"])


def decay_tensor(inputs, params):
    return params["a"] * pt.exp(-params["k"] * inputs["x"])


def setup():
    physics = kp.PhysicsModel(decay, PRIORS, inputs=["x"], name="decay")
    x = np.linspace(0.0, 3.0, 20)
    y = decay({"x": x}, TRUTH) + np.random.default_rng(1).normal(0.0, NOISE, x.size)
    data = kp.CalibrationData({"x": x}, y, noise_sd=NOISE)
    return physics, data, design_box(physics, data)


def accuracy(sizes: list[int]) -> pd.DataFrame:
    physics, _, box = setup()
    held = run_design(physics, space_filling_design(box, 200, method="sobol", seed=9))
    rows = []
    for kernel in ("matern52", "se"):
        for n in sizes:
            runs = run_design(physics, space_filling_design(box, n, seed=1))
            em = Emulator(runs, physics, box=box, kernel=kernel)
            out, loo = check_emulator(em, held, warn=False), check_emulator(em, warn=False)
            rows.append(
                {
                    "kernel": kernel,
                    "runs": n,
                    "held_out_coverage90": out.coverage,
                    "held_out_rel_rmse": out.relative_rmse,
                    "loo_coverage90": loo.coverage,
                    "loo_rel_rmse": loo.relative_rmse,
                }
            )
    return pd.DataFrame(rows).set_index("kernel")


def posteriors(cases: list[tuple[str, int, str]]) -> pd.DataFrame:
    physics, data, box = setup()
    direct = kp.PhysicsModel(decay_tensor, PRIORS, inputs=["x"], backend="pytensor")
    t0 = time.perf_counter()
    ref = kp.calibrate(direct, data, **SAMPLING).posterior
    rows = [{"model": "direct", "runs": 0, "wall_s": time.perf_counter() - t0}]
    for k in PRIORS:
        rows[0].update({f"{k}_mean": float(ref[k].mean()), f"{k}_sd": float(ref[k].std())})
    for kernel, n, covariance in cases:
        t0 = time.perf_counter()
        runs = run_design(physics, space_filling_design(box, n, seed=1))
        em = Emulator(runs, physics, box=box, kernel=kernel)
        post = kp.calibrate(em.physics_model(covariance=covariance), data, **SAMPLING).posterior
        row = {"model": f"{kernel}, {covariance}", "runs": n}
        row["wall_s"] = time.perf_counter() - t0
        for k in PRIORS:
            mean, sd = float(post[k].mean()), float(post[k].std())
            ref_mean, ref_sd = float(ref[k].mean()), float(ref[k].std())
            row.update(
                {
                    f"{k}_mean": mean,
                    f"{k}_sd": sd,
                    f"{k}_shift_in_direct_sd": (mean - ref_mean) / ref_sd,
                    f"{k}_sd_ratio": sd / ref_sd,
                    f"{k}_truth_in_own_sd": (mean - TRUTH[k]) / sd,
                }
            )
        rows.append(row)
    return pd.DataFrame(rows).set_index("model")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--quick", action="store_true", help="fewer sizes and cases")
    args = parser.parse_args(argv)
    logging.getLogger("pymc").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore")
    sizes = [30, 100] if args.quick else [30, 60, 100, 150]
    cases = [("se", 150, "full"), ("matern52", 15, "full")]
    if not args.quick:
        cases += [("matern52", 100, "full"), ("matern52", 15, "diagonal"), ("se", 8, "full")]
    table1 = accuracy(sizes)
    table2 = posteriors(cases)
    text = (
        "## Emulator accuracy (200 held-out Sobol runs; leave-one-out)\n\n"
        + markdown_table(table1)
        + "\n\n## Posteriors through the emulator vs the direct model (M0)\n\n"
        + markdown_table(table2)
        + "\n"
    )
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "emulator.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
