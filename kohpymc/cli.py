"""Command line: ``kohpymc study STUDY.toml [--out DIR]`` and ``kohpymc discover``.

``study`` runs :func:`kohpymc.run_study` on a study file (:mod:`kohpymc.config`),
printing one line per step while it samples and the validation table at the end.
``discover STUDY.toml [--json OUT] [--out DIR]`` runs :func:`kohpymc.discovery.discover`
on the same file.  Exit status 0 on success, 2 for a bad study file or data, 1 when
every formulation failed.
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


def _load(args: argparse.Namespace):
    """The study file, or None after printing the error (exit status 2)."""
    from kohpymc.config import StudyConfigError, load_study

    try:
        return load_study(args.study)
    except (StudyConfigError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return None


def _sampler_overrides(args: argparse.Namespace, sampling: dict) -> dict:
    """``[sampling]`` of the file with the command line's --draws/--tune/--chains/--seed."""
    out = dict(sampling)
    for key in ("draws", "tune", "chains"):
        if getattr(args, key) is not None:
            out[key] = getattr(args, key)
    if args.seed is not None:
        out["random_seed"] = args.seed
    return out


def _study(args: argparse.Namespace) -> int:
    from kohpymc.study import run_study

    spec = _load(args)
    if spec is None:
        return 2
    kwargs = spec.run_kwargs()
    kwargs.update(_sampler_overrides(args, spec.sampling))
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


def _discover(args: argparse.Namespace) -> int:
    import json

    import matplotlib.pyplot as plt
    import numpy as np

    from kohpymc.discovery import discover
    from kohpymc.plots import plot_residuals_before_after
    from kohpymc.study import write_atomic

    spec = _load(args)
    if spec is None:
        return 2
    merged = _sampler_overrides(args, spec.sampling)
    sampling = {k: v for k, v in merged.items() if k in ("draws", "tune", "chains")}
    seed = merged.get("random_seed")
    try:
        report = discover(
            spec.physics,
            spec.calibration,
            spec.validation,
            tolerance=spec.tolerance,
            random_seed=seed,
            progress=None if args.quiet else lambda msg: print(msg, flush=True),
            **sampling,
        )
    except (ValueError, KeyError, TypeError) as err:
        print(f"error: {spec.source}: {err}", file=sys.stderr)
        return 2
    payload = report.to_dict()
    text = json.dumps(payload, indent=2)
    print(text)
    if args.json:
        write_atomic(Path(args.json), lambda p: p.write_text(text + "\n"))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / "report.json", lambda p: p.write_text(text + "\n"))
        write_atomic(out / "before.nc", lambda p: report.before.to_netcdf(str(p)))
        write_atomic(out / "after.nc", lambda p: report.after.to_netcdf(str(p)))
        cal = spec.calibration
        key = report.inputs[0] if report.inputs else spec.physics.inputs[0]
        resid = [
            cal.y - report_physics.evaluate(cal.inputs, _posterior_mean(idata, report_physics))
            for report_physics, idata in (
                (spec.physics, report.before),
                (report.physics, report.after),
            )
        ]
        others = [k for k in report.inputs if k != key]
        groups = None
        if others:
            groups = np.array([", ".join(f"{k}={cal.inputs[k][i]:g}" for k in others)
                               for i in range(cal.n)])  # fmt: skip
        fig = plot_residuals_before_after(
            cal.inputs[key], resid[0], resid[1], x_name=key, groups=groups, noise_sd=cal.noise_sd
        )
        write_atomic(out / "residuals.png", lambda p: fig.savefig(p, dpi=120, format="png"))
        plt.close(fig)
    return 0


def _posterior_mean(idata, physics) -> dict[str, float]:
    return {k: float(idata.posterior[k].mean()) for k in physics.parameters}


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
    common = argparse.ArgumentParser(add_help=False)  # options both commands take
    for key in ("draws", "tune", "chains", "seed"):
        common.add_argument(f"--{key}", type=int, help=f"override [sampling] {key}")
    common.add_argument("--quiet", action="store_true", help="no progress lines")
    study = sub.add_parser(
        "study", parents=[common], help="calibrate, validate and weigh formulations"
    )
    study.add_argument("study", help="study TOML file")
    study.add_argument("--out", help="output folder (default: [output] dir of the file)")
    study.add_argument("--no-figures", action="store_true", help="skip the figures")
    study.add_argument("--progressbar", action="store_true", help="PyMC's progress bar")
    study.set_defaults(run=_study)
    disc = sub.add_parser("discover", parents=[common], help="find, name and add a missing effect")
    disc.add_argument("study", help="study TOML file (same format as `kohpymc study`)")
    disc.add_argument("--json", help="write the JSON report here")
    disc.add_argument("--out", help="folder for report.json, before/after NetCDF, figure")
    disc.set_defaults(run=_discover)
    args = parser.parse_args(argv)
    _quiet_libraries()
    return args.run(args)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
