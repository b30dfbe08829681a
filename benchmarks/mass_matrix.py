"""nutpie's low-rank mass-matrix adaptation against its diagonal one, in the same run.

Issue 15 asks to use nutpie's low-rank modified mass matrix "where it helps (measure)".
For each case (the beam with known noise and the two-load beam with the noise sd
calibrated, under M0, M2 and M4; the three hard posteriors of
:mod:`kohpymc.examples.hard_posteriors` under M0) this calls :func:`kohpymc.calibrate`
with the library's defaults (nutpie in coordinates whitened at the posterior mode), once
with the diagonal adaptation and once with ``low_rank_modified_mass_matrix=True``, the
two interleaved, and reports the sampling seconds, the leapfrog steps per draw, the
smallest bulk ESS over the free parameters, ESS per second of sampling and divergences.
``ess_per_s_ratio`` is low-rank over diagonal (above 1: low rank is faster).

Run ``python -m benchmarks.mass_matrix`` (``--quick`` for 300 draws); the table goes to
``<out>/mass_matrix.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

import kohpymc as kp
from benchmarks.usable import Case, cases, diagnostics

#: (problem, formulations) measured
CASES = (
    ("beam", ("M0", "M2", "M4")),
    ("beam-2load", ("M0", "M2", "M4")),
    ("arrhenius", ("M0",)),
    ("collinear", ("M0",)),
    ("multiplicative", ("M0",)),
)
ADAPTATIONS = {"diagonal": {}, "low-rank": {"low_rank_modified_mass_matrix": True}}


def measure(case: Case, kwargs: dict[str, Any], *, draws: int, tune: int, seed: int) -> dict:
    """One calibration: sampling seconds, steps per draw, min ESS_bulk, divergences."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = kp.calibrate(
            case.physics, case.data, case.discrepancy, draws=draws, tune=tune, chains=4,
            random_seed=seed, warn=False, **kwargs,
        )  # fmt: skip
    idata = cal.idata
    names = [rv.name for rv in cal.built.model.free_RVs if rv.name in idata.posterior]
    diag = diagnostics(idata, names)
    timings = json.loads(idata.attrs["sampling"]).get("timings_s", {})
    seconds = float(timings.get("sampling", sum(timings.values())))
    steps = float(idata.sample_stats["n_steps"].mean())
    return {
        "sampling_s": seconds,
        "steps_per_draw": steps,
        "min_ess_bulk": diag["min_ess_bulk"],
        "ess_per_s": diag["min_ess_bulk"] / seconds,
        "max_rhat": diag["max_rhat"],
        "divergences": int(idata.sample_stats["diverging"].sum()),
    }


def mass_matrix_table(*, draws: int, tune: int, seed: int) -> pd.DataFrame:
    """Both adaptations on every case of :data:`CASES`, interleaved."""
    rows = []
    for problem, labels in CASES:
        for case in cases([problem], labels, seed=0):
            for name, kwargs in ADAPTATIONS.items():
                row = measure(case, kwargs, draws=draws, tune=tune, seed=seed)
                rows.append({"problem": case.problem, "formulation": case.formulation,
                             "adaptation": name, **row})  # fmt: skip
                print(f"{case.problem} {case.formulation} {name}: {row}", flush=True)
    frame = pd.DataFrame(rows).set_index(["problem", "formulation", "adaptation"])
    ratio = frame["ess_per_s"].xs("low-rank", level=2) / frame["ess_per_s"].xs("diagonal", level=2)
    frame["ess_per_s_ratio"] = ratio.reindex(frame.index.droplevel(2)).to_numpy()
    return frame


def main(argv: Sequence[str] | None = None) -> pd.DataFrame:
    """Run, print and write ``mass_matrix.md``; return the frame."""
    from benchmarks.run import _quiet
    from kohpymc.study_files import markdown_table, write_atomic

    parser = argparse.ArgumentParser(prog="python -m benchmarks.mass_matrix", description=__doc__)
    parser.add_argument("--draws", type=int, default=1000)
    parser.add_argument("--tune", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--quick", action="store_true", help="300 draws, 300 tuning steps")
    parser.add_argument("--out", default="benchmarks/results")
    args = parser.parse_args(argv)
    _quiet()
    if args.quick:
        args.draws, args.tune = 300, 300
    machine = f"{platform.node()} ({os.cpu_count()} cores), {time.strftime('%Y-%m-%d %H:%M')}"
    frame = mass_matrix_table(draws=args.draws, tune=args.tune, seed=args.seed)
    header = (f"# nutpie mass-matrix adaptation: diagonal vs low-rank\n\n{machine}; "
              f"4 chains x ({args.tune} + {args.draws}), seed {args.seed}; load "
              f"{os.getloadavg()[0]:.1f} at the end\n")  # fmt: skip
    text = header + "\n" + markdown_table(frame.reset_index().set_index("problem"), digits=3)
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "mass_matrix.md", lambda p: p.write_text(text + "\n"))
    return frame


if __name__ == "__main__":
    main()
