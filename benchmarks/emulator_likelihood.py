"""Cost of one log density + gradient of the emulated dielectric calibration.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.emulator_likelihood [--mode NUMBA]
        [--formulations M0 M2 M4] [--repeats 15] [--evaluations 20]

Issue 18: the principal-component emulator's ``Σ_η(θ)`` enters the likelihood covariance.
This builds the emulator of ``benchmarks/dielectric_emulator.py`` (same design, 250 runs,
cached in ``--cache``), composes the calibration model of each formulation with
``physics_model(covariance="full")`` (diagonal plus low rank: Woodbury likelihood) and
``covariance="dense"`` (the ``n × n`` matrix factorized at every evaluation; and with
``--covariances ... diagonal`` the diagonal alone, the emulator's own cost), compiles
``(log p, ∇ log p)`` over the free variables in ``--mode`` (NUMBA: what nutpie runs) and
times them interleaved in this process at the least-squares fit: ``--repeats`` rounds,
each timing ``--evaluations`` calls of every function in turn.  Reports the median
seconds per evaluation and the dense / full ratios of the rounds.  The two log densities
are also compared (they must agree to rounding).
"""

from __future__ import annotations

import argparse
import os
import pickle
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytensor  # noqa: E402

from benchmarks import dielectric_emulator as bench  # noqa: E402
from kohpymc.emulator import FunctionalEmulator, run_curves  # noqa: E402
from kohpymc.examples import dielectric as d  # noqa: E402
from kohpymc.model import compose_model  # noqa: E402


def emulator(cache: Path) -> tuple[FunctionalEmulator, object, dict]:
    """The benchmark's emulator, calibration data and least-squares fit (pickled once)."""
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    cal, _ = bench.problem()
    fit = d.least_squares_fit(cal)
    center, matrix, logged = bench.laplace_rotation(cal, fit)
    design = bench.whitened_design(center, matrix, logged, 250, 5.0, seed=1)
    runs = run_curves(d.physics_model(), design, d.design(40))
    em = FunctionalEmulator(
        runs,
        d.physics_model(),
        variance=0.99999,
        log_parameters=bench.LOG_PARAMS,
        rotation=(center, matrix),
        kernel="se",
        restarts=2,
    )
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_bytes(pickle.dumps((em, cal, fit)))
    return em, cal, fit


def value_and_gradient(em, cal, fit, formulation, covariance: str, mode: str):
    """Compiled ``point -> (log p, ∇ log p)`` and the point (the fit, other variables initial)."""
    model = compose_model(em.physics_model(covariance=covariance, confine=True), cal, formulation)
    model = model.model
    point = model.initial_point()
    for rv, value in model.rvs_to_values.items():
        if rv.name in fit:
            tr = model.rvs_to_transforms[rv]
            v = np.asarray(fit[rv.name], dtype=float)
            point[value.name] = tr.forward(v, *rv.owner.inputs).eval() if tr else v
    logp = model.logp()
    grads = pytensor.grad(logp, model.value_vars)
    fn = pytensor.function(model.value_vars, [logp, *grads], mode=mode)
    args = [point[v.name] for v in model.value_vars]
    return (lambda: fn(*args)), model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", default="NUMBA")
    parser.add_argument("--formulations", nargs="+", default=["M0", "M2", "M4"])
    parser.add_argument("--covariances", nargs="+", default=["full", "dense"])
    parser.add_argument("--dense-only", nargs="*", default=["M4"])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--evaluations", type=int, default=20)
    parser.add_argument("--cache", default="/tmp/pca/dielectric_emulator.pkl")
    args = parser.parse_args()
    bench.quiet()
    em, cal, fit = emulator(Path(args.cache))
    print(em, f"rows {cal.n}", flush=True)
    forms = d.formulations()
    functions = {}
    for label in args.formulations:
        modes = ("dense",) if label in args.dense_only else args.covariances
        for covariance in modes:
            t0 = time.perf_counter()
            fn, _ = value_and_gradient(em, cal, fit, forms[label], covariance, args.mode)
            values = fn()
            print(
                f"{label} {covariance}: log p {float(values[0]):.10g}, compiled in "
                f"{time.perf_counter() - t0:.0f} s",
                flush=True,
            )
            functions[(label, covariance)] = fn
    times = {key: [] for key in functions}
    for _ in range(args.repeats):
        for key, fn in functions.items():
            t0 = time.perf_counter()
            for _ in range(args.evaluations):
                fn()
            times[key].append((time.perf_counter() - t0) / args.evaluations)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; mode {args.mode}")
    medians = {key: float(np.median(v)) for key, v in times.items()}
    for (label, covariance), sec in medians.items():
        line = f"{label} {covariance}: {1e3 * sec:.3f} ms per log p + gradient"
        if covariance == "dense" and (label, "full") in medians:
            ratios = np.array(times[(label, "dense")]) / np.array(times[(label, "full")])
            line += (
                f"; dense / full per round: median {np.median(ratios):.1f} "
                f"(range {ratios.min():.1f}-{ratios.max():.1f})"
            )
        print(line)


if __name__ == "__main__":
    main()
