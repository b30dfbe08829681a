"""``make bench``: kohpymc against random-walk Metropolis and surmise, study wall time, scale.

Run from the repository root::

    python -m benchmarks.run [--quick] [--only beam|study|scale|usable] [--out benchmarks/results]

In one process and on the same data it runs, per beam formulation M0–M5,

* kohpymc with PyMC's NUTS (C backend and NUMBA mode) and with nutpie (:mod:`benchmarks.beam`),
* the paper's sampler, random-walk Metropolis on a numpy log posterior of the same model
  (:mod:`benchmarks.baselines`, 2 chains × 250,000 draws),
* surmise's calibrator for M0 (known noise; :mod:`benchmarks.surmise_baseline`),

then the whole beam study (M0–M4 + validation + combination) end to end, the
n = 9,120 GP-discrepancy calibration (:mod:`benchmarks.scale`) and the time to a usable
posterior (every free parameter at ESS_bulk >= 1000 and r̂ <= 1.01, compilation included;
beam, two-load beam with unknown noise and the hard synthetic problems;
:mod:`benchmarks.usable`).  Tables go to the terminal and to ``<out>/beam.csv``,
``beam.md``, ``study.json``, ``scale.json``, ``usable.csv``, ``usable.md``.
Ratios are ESS/s of E (bulk ESS over the sampler's own seconds) of kohpymc over the
baseline in the same run.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

LABELS = ("M0", "M1", "M2", "M3", "M4", "M5")
COLUMNS = [
    "formulation",
    "sampler",
    "wall_s",
    "compile_s",
    "sampling_s",
    "ess_bulk_E",
    "ess_tail_E",
    "ess_per_s_E",
    "rhat_E",
    "divergences",
    "mean_E",
    "sd_E",
    "ratio_vs_rwm",
    "ratio_vs_surmise",
]


def markdown_table(frame: pd.DataFrame, digits: int = 4) -> str:
    """A GitHub pipe table of ``frame`` (index first), floats to ``digits`` significant digits.

    Parameters
    ----------
    frame : pandas.DataFrame
        Rows to print; the index name heads the first column (default "formulation").
    digits : int
        Significant digits of float cells; NaN cells are left empty.

    Returns
    -------
    str

    Examples
    --------
    >>> print(markdown_table(pd.DataFrame({"ess": [812.345, np.nan]}, index=["M0", "M1"]), 2))
    | formulation | ess |
    |---|---|
    | M0 | 8.1e+02 |
    | M1 |  |
    """

    def cell(value: Any) -> str:
        if isinstance(value, float | np.floating):
            return "" if np.isnan(value) else f"{value:.{digits}g}"
        return str(value).replace("|", "\\|")

    header = [frame.index.name or "formulation", *map(str, frame.columns)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for index, row in frame.iterrows():
        lines.append("| " + " | ".join([cell(index), *(cell(v) for v in row)]) + " |")
    return "\n".join(lines)


def _quiet() -> None:
    for name in ("pymc", "pytensor", "pytensor.tensor.blas", "nutpie"):
        logging.getLogger(name).setLevel(logging.ERROR)
    import warnings

    warnings.filterwarnings("ignore")


def beam_table(quick: bool = False, seed: int = 2026) -> pd.DataFrame:
    """All beam rows (kohpymc pymc/nutpie, random walk, surmise) with the ratios.

    Parameters
    ----------
    quick : bool
        Short runs (a smoke test of the harness; the numbers are not the benchmark).
    seed : int
        Seed of every sampler.
    """
    from benchmarks.baselines import run_baseline
    from benchmarks.beam import run_kohpymc

    rows: list[dict[str, Any]] = []
    rwm_draws, nuts_draws = (5_000, 300) if quick else (250_000, 2_000)
    for label in LABELS:
        rwm = run_baseline(label, draws=rwm_draws, tune=min(20_000, rwm_draws), seed=seed)
        rwm = {
            **rwm,
            "sampler": "random-walk Metropolis",
            "sampling_s": rwm["wall_s"],
            "compile_s": rwm["setup_s"],
            "wall_s": rwm["wall_s"] + rwm["setup_s"],
            "divergences": 0,
        }
        rows.append(rwm)
        for sampler in ("pymc", "pymc-numba", "nutpie"):
            row = run_kohpymc(label, sampler, draws=nuts_draws, tune=1000, seed=seed)
            row["ratio_vs_rwm"] = row["ess_per_s_E"] / rwm["ess_per_s_E"]
            rows.append(row)
        print(f"  {label} done", flush=True)
    try:
        from benchmarks.surmise_baseline import run_surmise
    except ImportError as err:  # surmise is a bench-only extra
        print(f"  surmise not available ({err}); skipped")
    else:
        sur = run_surmise(seed=seed, samples=2_000 if quick else 10_000)
        sur = {
            **sur,
            "formulation": "M0",
            "sampler": "surmise",
            "sampling_s": sur["wall_s"],
            "compile_s": sur["setup_s"],  # the emulator fit
            "wall_s": sur["wall_s"] + sur["setup_s"],
        }
        rows.append(sur)
        for row in rows:
            if row["formulation"] == "M0" and row["sampler"].startswith("kohpymc"):
                row["ratio_vs_surmise"] = row["ess_per_s_E"] / sur["ess_per_s_E"]
    frame = pd.DataFrame(rows)
    for col in COLUMNS:
        if col not in frame:
            frame[col] = float("nan")
    return frame[COLUMNS]


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="short runs (harness smoke test)")
    parser.add_argument("--only", choices=["beam", "study", "scale", "usable"], action="append")
    parser.add_argument("--out", default="benchmarks/results", help="output folder")
    args = parser.parse_args(argv)
    parts = args.only or ["beam", "study", "scale", "usable"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _quiet()
    machine = f"{platform.node()} ({os.cpu_count()} cores), {time.strftime('%Y-%m-%d %H:%M')}"
    print(f"kohpymc benchmark on {machine}", flush=True)

    if "beam" in parts:
        print("beam problem (n = 20), formulations M0–M5:", flush=True)
        frame = beam_table(args.quick)
        frame.to_csv(out / "beam.csv", index=False)
        md = markdown_table(frame.set_index("formulation"), digits=3)
        (out / "beam.md").write_text(f"Beam benchmark, {machine}\n\n{md}\n")
        print(md, flush=True)

    if "study" in parts:
        from benchmarks.beam import run_study

        print("whole beam study (M0–M4 + validation + combination):", flush=True)
        # the shipped file as it is; the physics as a PyTensor expression compiled by numba
        # (its first run pays numba's compilation, in-process and on disk); one formulation
        # at a time with parallel chains, or two at a time with sequential chains; PyMC's
        # default warm-up (1000) and a shorter one (500) that these small models need
        draws = 300 if args.quick else 1000
        runs = [
            run_study(draws=draws, tune=tune, numba=numba, workers=workers)
            for numba, tune, workers in (
                (False, 1000, 1),
                (False, 1000, 2),
                (True, 1000, 1),
                (True, 1000, 2),
                (True, 500, 2),
            )
        ]
        (out / "study.json").write_text(json.dumps(runs, indent=2))
        print(json.dumps(runs, indent=2), flush=True)

    if "scale" in parts:
        from benchmarks import scale

        print("n = 9,120 GP discrepancy:", flush=True)
        result = scale.main(["--cores", "2"] + (["--quick"] if args.quick else []))
        # the same data through the library: one kohpymc.calibrate call with GridGP
        result["library"] = scale.run_library(args.quick, cores=2)
        (out / "scale.json").write_text(json.dumps(result, indent=2, default=str))

    if "usable" in parts:
        from benchmarks import usable

        print("time to a usable posterior (ESS_bulk >= 1000, r_hat <= 1.01):", flush=True)
        usable.main(["--out", str(out)] + (["--quick"] if args.quick else []))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
