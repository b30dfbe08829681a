"""Command line: ``kohpymc study STUDY.toml [--out DIR]``.

Runs :func:`kohpymc.run_study` on a study file (:mod:`kohpymc.config`), printing one
line per step while it samples and the validation table at the end.  Exit status 0 on
success, 2 for a bad study file or data, 1 when every formulation failed.
"""

from __future__ import annotations

import argparse
import logging
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

__all__ = ["main"]


def _quiet_libraries() -> None:
    logging.getLogger("pymc").setLevel(logging.ERROR)
    logging.getLogger("pytensor.tensor.blas").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message="PyTensor could not link to a BLAS")
    warnings.filterwarnings("ignore", category=FutureWarning)
    warnings.filterwarnings("ignore", message="The effective sample size per chain")


def _study(args: argparse.Namespace) -> int:
    from kohpymc.config import StudyConfigError, load_study
    from kohpymc.study import run_study

    try:
        spec = load_study(args.study)
    except (StudyConfigError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    kwargs = spec.run_kwargs()
    for key in ("draws", "tune", "chains"):
        if getattr(args, key) is not None:
            kwargs[key] = getattr(args, key)
    if args.seed is not None:
        kwargs["random_seed"] = args.seed
    out = Path(args.out) if args.out else spec.out_dir
    print(
        f"study {spec.source}: physics {spec.physics.name!r} "
        f"({', '.join(spec.physics.parameters)}), {spec.calibration.n} calibration and "
        f"{spec.validation.n} validation rows, formulations {', '.join(spec.formulations)}"
    )
    try:
        result = run_study(
            **kwargs,
            out_dir=out,
            figures=not args.no_figures,
            progress=None if args.quiet else lambda msg: print(msg, flush=True),
            progressbar=args.progressbar,
        )
    except (ValueError, KeyError) as err:
        print(f"error: {spec.source}: {err}", file=sys.stderr)
        return 2
    except RuntimeError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print()
    print(result.summary())
    if result.failures:
        print("\nfailed: " + "; ".join(f"{k}: {v}" for k, v in result.failures.items()))
    print(f"\nresults in {out}/ (table.md, table.csv, *.nc, figures)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``kohpymc`` command.

    Examples
    --------
    >>> main(["study", "no-such-file.toml"])
    2
    """
    parser = argparse.ArgumentParser(
        prog="kohpymc", description="Bayesian calibration with model discrepancy."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    study = sub.add_parser("study", help="calibrate, validate and weigh formulations")
    study.add_argument("study", help="study TOML file")
    study.add_argument("--out", help="output folder (default: [output] dir of the file)")
    study.add_argument("--draws", type=int, help="override [sampling] draws")
    study.add_argument("--tune", type=int, help="override [sampling] tune")
    study.add_argument("--chains", type=int, help="override [sampling] chains")
    study.add_argument("--seed", type=int, help="override [sampling] seed")
    study.add_argument("--no-figures", action="store_true", help="skip the figures")
    study.add_argument("--quiet", action="store_true", help="no progress lines")
    study.add_argument("--progressbar", action="store_true", help="PyMC's progress bar")
    study.set_defaults(run=_study)
    args = parser.parse_args(argv)
    _quiet_libraries()
    return args.run(args)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
