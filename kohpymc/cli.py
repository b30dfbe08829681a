"""Command line: ``kohpymc study STUDY.toml [--out DIR]``, ``kohpymc discover``, ``kohpymc check``.

``study`` runs :func:`kohpymc.run_study` on a study file (:mod:`kohpymc.config`),
showing each formulation's progress (:mod:`kohpymc.progress`: live lines on a terminal,
plain lines otherwise, nothing with ``--quiet``) and the validation table at the end;
``--workers N`` / ``--scheduler ADDRESS`` run the formulations on a Dask cluster
(:mod:`kohpymc.execution`).  Each formulation's results are written to the output folder
as soon as they are finished; running the same command again reuses every formulation
whose inputs are unchanged ("M0: reused"), ``--fresh`` recomputes all.
``discover STUDY.toml [--json OUT] [--out DIR]`` runs :func:`kohpymc.discovery.discover`
on the same file.  Exit status 0 on success, 2 for a bad study file or data, 1 when
every formulation failed.

``--dry-run`` (every command) reads and checks the study file, its data, the physics
function at the prior centre, priors, formulations, options and output paths, prints a
summary and exits 0 without sampling or writing.  Bad input of any kind exits 2 with one
``error:`` line naming the file and the key, column or option, and writes nothing.

``check STUDY.toml --replicates N`` runs simulation-based calibration
(:func:`kohpymc.sbc.check_calibration`) and prints the coverage table and the verdict.
Exit status 0 on PASS, 3 on FAIL (the set-up does not recover the truth), 2 for bad
input, 1 when no replicate could be fitted.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

from kohpymc.warning_filters import quiet_command_line

__all__ = ["main"]


def _load(args: argparse.Namespace):
    """The study file, or None after printing the error (exit status 2)."""
    from kohpymc.config import StudyConfigError, load_study

    try:
        return load_study(args.study)
    except StudyConfigError as err:
        _bad_input(err)
        return None


def _bad_input(err: Exception) -> int:
    """Print a bad-input error (it names the file and the key) and return exit status 2."""
    print(f"error: {err}", file=sys.stderr)
    return 2


def _checked_options(
    args: argparse.Namespace, spec, folders: Sequence[Path], files: Sequence[Path] = ()
) -> None:
    """The command line's numbers and output paths, checked before anything runs.

    Raises :class:`~kohpymc.config.StudyConfigError` naming the option (``--draws``) or the
    output path; the checks are :mod:`kohpymc.checks`'.
    """
    from kohpymc.checks import check_count, check_output_path
    from kohpymc.config import StudyConfigError

    try:
        for key in ("draws", "tune", "chains", "replicates", "rank_draws"):
            if getattr(args, key, None) is not None:
                check_count(getattr(args, key), f"--{key.replace('_', '-')}")
        if args.seed is not None:
            check_count(args.seed, "--seed", minimum=0)
        for path in folders:
            check_output_path(path)
        for path in files:
            check_output_path(path, folder=False)
    except ValueError as err:
        raise StudyConfigError(f"{spec.source}: {err}") from err


def _checked_build(spec, formulations, compose=None) -> None:
    """Every formulation's model composes on the calibration data (before any sampling)."""
    from kohpymc.checks import FormulationBuildError, check_formulations_build
    from kohpymc.config import StudyConfigError

    try:
        check_formulations_build(spec.physics, spec.calibration, formulations, compose)
    except FormulationBuildError as err:
        raise StudyConfigError(f"{spec.source}: [formulations.{err.label}] {err}") from err


def _output_rows(spec: Any) -> str:
    """``calibration rows u 30, strain 28; validation rows ...``, saying why they differ.

    An empty or NaN cell of an output leaves that row out for that output only; the
    counts make such cells visible rather than silent.
    """
    parts, uneven = [], False
    for what, data in (("calibration", spec.calibration), ("validation", spec.validation)):
        sizes = data.sizes
        uneven |= len(set(sizes.values())) > 1
        parts.append(f"{what} rows " + ", ".join(f"{k} {n}" for k, n in sizes.items()))
    why = " (an empty or NaN cell leaves its row out for that output only)" if uneven else ""
    return "; ".join(parts) + why


def _checked_multi_output_build(spec) -> None:
    """Every formulation's joint model composes on the calibration data (before sampling)."""
    from kohpymc.multi_output.model import compose_multi_output_model

    _checked_build(spec, spec.formulations, compose=compose_multi_output_model)


def _dry_run_summary(spec, what: str, outputs: Sequence[Path], detail: str = "") -> int:
    """The ``--dry-run`` report: what was checked and what a real run would do."""
    print(
        f"dry run: {spec.source} is ready for `kohpymc {what}`: physics "
        f"{spec.physics.name!r} ({', '.join(spec.physics.parameters)}) runs on "
        f"{spec.calibration.n} calibration and {spec.validation.n} validation rows at the "
        f"prior centre; formulations {', '.join(spec.formulations)}"
        + (" (each builds on the calibration data)" if what != "discover" else "")
    )
    if detail:
        print(detail)
    where = ", ".join(str(p) for p in outputs) or "nowhere (no output asked for)"
    print(f"would write to {where}; nothing sampled, nothing written")
    return 0


def _sampler_overrides(args: argparse.Namespace, sampling: dict) -> dict:
    """``[sampling]`` of the file with the command line's --draws/--tune/--chains/--seed."""
    out = dict(sampling)
    for key in ("draws", "tune", "chains"):
        if getattr(args, key) is not None:
            out[key] = getattr(args, key)
    if args.seed is not None:
        out["random_seed"] = args.seed
    return out


def _execution_overrides(args: argparse.Namespace, execution: dict) -> dict:
    """``[execution]`` of the file, or the command line's --workers / --scheduler."""
    if args.workers is not None:
        return {"workers": args.workers, "scheduler": None}
    if args.scheduler is not None:
        return {"workers": 1, "scheduler": args.scheduler}
    return dict(execution)


def _emulated_physics(spec: Any, kwargs: dict, out: Path) -> Any:
    """The study's physics replaced by its emulator (``[emulator]``; runs cached in out)."""
    from kohpymc.emulator.study import study_physics

    sampling = _round_sampling(kwargs)
    physics = study_physics(
        spec.emulator,
        kwargs["physics"],
        kwargs["calibration"],
        out,
        formulations=kwargs["formulations"],
        sampling=sampling,
        workers=kwargs.get("workers", 1),
        scheduler=kwargs.get("scheduler"),
        validation=kwargs["validation"],
    )
    runs = physics.emulator.runs
    print(
        f"emulator: {physics.emulator!r}; {runs.simulated} run(s) simulated now, "
        f"{runs.cached} from {out}/emulator/runs/ (checks in {out}/emulator/)"
    )
    _say_refinement(spec.emulator, out / "emulator")
    _say_skipped_rounds(out / "emulator")
    return physics


def _posterior_rounds(spec: Any, kwargs: dict, out: Path, result: Any, run: Any) -> Any:
    """``[emulator] refine_at_posterior``: runs where the emulator is unfit, study again.

    A formulation whose posterior mean the emulator missed (its ``physics_problems``)
    gets runs at its posterior (:func:`kohpymc.emulator.study.posterior_round`); the
    study then runs again through the refitted emulator, and the record says how far
    each posterior moved.  ``kwargs["physics"]`` becomes the refitted emulator.
    """
    from kohpymc.calibration import physics_problems
    from kohpymc.emulator.posterior_rounds import posterior_moves
    from kohpymc.emulator.study import posterior_round

    while True:
        unfit = {k: idata for k, idata in result.results.items() if physics_problems(idata)}
        if not unfit:
            return result
        refined = posterior_round(
            spec.emulator, kwargs["physics"], kwargs["calibration"], unfit, out,
            formulations=kwargs["formulations"], sampling=_round_sampling(kwargs),
            workers=kwargs.get("workers", 1), scheduler=kwargs.get("scheduler"),
            validation=kwargs["validation"],
        )  # fmt: skip
        if refined is None:
            return result
        kwargs["physics"], record = refined
        last = record.rounds[-1]
        print(
            f"emulator unfit where the posterior of {', '.join(unfit)} lies: "
            f"{last['runs_added']} runs added there ({last['runs']} in all); calibrating again"
        )
        before = result.results
        result = run()
        params = list(kwargs["physics"].parameters)
        last["moved"] = posterior_moves(before, result.results, params)
        last["still_unfit"] = {
            k: physics_problems(idata) for k, idata in result.results.items()
            if physics_problems(idata)
        }  # fmt: skip
        record.write(out / "emulator")
        _say_moves(last["moved"], out / "emulator")


def _say_moves(moved: dict[str, dict[str, float]], folder: Path) -> None:
    """One line: how far each formulation's posterior mean moved after a posterior round."""
    from kohpymc.emulator.posterior_rounds import POSTERIOR_RECORD

    parts = [
        f"{label} " + ", ".join(f"{k} {v:+.2f}" for k, v in moves.items())
        for label, moves in sorted(moved.items())
    ]
    print(
        f"after the round at the posteriors the posterior means moved (in their sds): "
        f"{'; '.join(parts)} ({folder}/{POSTERIOR_RECORD})"
    )


def _round_sampling(kwargs: dict) -> dict:
    """The sampler settings the emulator's rounds are keyed on."""
    return {k: kwargs[k] for k in ("draws", "tune", "chains", "random_seed") if k in kwargs}


def _say_skipped_rounds(folder: Path) -> None:
    """One line when the sequential rounds were skipped (``rounds.csv``'s reason)."""
    import pandas as pd

    path = folder / "rounds.csv"
    if not path.is_file():
        return
    table = pd.read_csv(path)
    if "skipped" in table.columns:
        print(f"sequential rounds skipped: {table['skipped'].iloc[0]} ({path})")


def _say_refinement(settings: Any, folder: Path) -> None:
    """One line on the refinement rounds at the data (``refine_at_data.json``), if any ran."""
    import json

    from kohpymc.emulator.study import REFINEMENT_RECORD

    path = folder / REFINEMENT_RECORD
    if settings.refine_at_data == 0 or not path.is_file():
        return
    record = json.loads(path.read_text())
    last = record["rounds"][-1]["check"]
    outcome = "passes" if record["passed"] else "STILL FAILS (see the warning above)"
    checks = last.get("outputs", {"": last})  # several outputs: one check each
    errors = ", ".join(
        f"{k + ' ' if k else ''}rms {c['rmse']:.3g} against the simulator's misfit "
        f"{c['misfit']:.3g}"
        for k, c in checks.items()
    )
    print(
        f"emulator check at the data: {len(record['rounds']) - 1} refinement round(s) added "
        f"{record['added_runs']} runs; at the best fit the emulator's error is {errors}: "
        f"{outcome} ({folder}/{REFINEMENT_RECORD})"
    )


def _emulated_outputs(spec: Any, execution: dict, out: Path) -> Any:
    """A multi-output study with its physics replaced by one emulator per output."""
    from dataclasses import replace

    from kohpymc.emulator import EmulatedPhysics
    from kohpymc.multi_output.emulator import study_outputs_physics

    physics = study_outputs_physics(
        spec.emulator,
        spec.physics,
        spec.calibration,
        out,
        workers=execution.get("workers", 1),
        scheduler=execution.get("scheduler"),
        validation=spec.validation,
    )
    emulators = {k: cast(EmulatedPhysics, physics.output(k)).emulator for k in physics.outputs}
    runs = next(iter(emulators.values())).runs
    print(
        f"emulator: {len(runs.points)} runs ({runs.simulated} simulated, {runs.cached} from "
        f"{out}/emulator/runs/), one GP per output (checks in {out}/emulator/<output>/)"
    )
    for name, emulator in emulators.items():
        print(f"  {name}: {emulator!r}")
    _say_refinement(spec.emulator, out / "emulator")
    return replace(spec, physics=physics)


def _emulator_note(spec: Any, what: str) -> None:
    """Say that ``[emulator]`` is for ``kohpymc study``: ``check``/``discover`` run the physics."""
    if spec.emulator is not None:
        print(
            f"note: {spec.source}: [emulator] is used by `kohpymc study` only; `kohpymc {what}` "
            "calls the physics function itself at every evaluation (no emulator)"
        )


def _lists_outputs(path: str) -> bool:
    """Whether a study file's ``[physics] output`` is a list (a multi-output study)."""
    import tomllib

    try:
        with open(path, "rb") as handle:
            doc = tomllib.load(handle)
    except (OSError, ValueError):  # unreadable, not UTF-8, not TOML
        return False  # load_study reports each of these, naming the file
    physics = doc.get("physics")
    return isinstance(physics, dict) and isinstance(physics.get("output"), list)


def _multi_output_study(args: argparse.Namespace) -> int:
    """``kohpymc study`` on a file with several outputs: joint calibration per formulation.

    Writes ``<label>.nc`` per formulation the moment it is sampled, and
    ``table.csv``/``table.md`` (one row per output and a combined row per formulation) at
    the end, each atomically; a rerun into the same folder reuses unchanged formulations
    (``--fresh`` recomputes them) and a failed formulation does not stop the others.
    """
    from kohpymc.checks import check_execution
    from kohpymc.config import StudyConfigError
    from kohpymc.multi_output import load_multi_output_study, run_multi_output_study
    from kohpymc.progress import task_display

    try:
        spec = load_multi_output_study(args.study)
        execution = _execution_overrides(args, spec.execution)
        try:
            check_execution(execution.get("workers", 1), execution.get("scheduler"))
        except ValueError as err:
            raise StudyConfigError(f"{spec.source}: --workers/--scheduler: {err}") from err
        out = Path(args.out) if args.out else spec.out_dir
        _checked_options(args, spec, [out])
        _checked_multi_output_build(spec)
    except StudyConfigError as err:
        return _bad_input(err)
    overrides = _sampler_overrides(args, {})
    outputs = ", ".join(spec.physics.outputs)
    if args.dry_run:
        print(
            f"dry run: {spec.source} is a multi-output study (outputs {outputs}; "
            f"parameters {', '.join(spec.physics.parameter_names)}; {_output_rows(spec)}); "
            "formulations "
            f"{', '.join(spec.formulations)} (each builds on the calibration data)\n"
            + (
                f"[emulator]: {spec.emulator.runs} simulator runs (each giving every output), "
                "one GP emulator per output\n"
                if spec.emulator is not None
                else ""
            )
            + f"would write to {out}; nothing sampled, nothing written"
        )
        return 0
    print(
        f"study {spec.source}: outputs {outputs} ({_output_rows(spec)}), formulations "
        f"{', '.join(spec.formulations)}"
    )
    display = task_display(sys.stdout, quiet=args.quiet)
    try:
        if spec.emulator is not None:
            spec = _emulated_outputs(spec, execution, out)
        result = run_multi_output_study(
            spec,
            out_dir=out,
            fresh=args.fresh,
            figures=not args.no_figures,
            progress=None if args.quiet else display.write,
            display=display,
            workers=execution.get("workers", 1),
            scheduler=execution.get("scheduler"),
            **overrides,
        )
    except (ValueError, KeyError) as err:
        print(f"error: {spec.source}: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # e.g. the Dask scheduler is unreachable
        print(f"error: {err}", file=sys.stderr)
        return 1
    finally:
        display.close()
    if result.failures:
        failed = "; ".join(f"{k}: {v}" for k, v in result.failures.items())
        print(f"failed: {failed}", file=sys.stderr)
    if not result.reliabilities:
        print(f"error: no formulation finished (see {out}/study.json)", file=sys.stderr)
        return 1
    print()
    print(result.table.to_string(float_format=lambda v: f"{v:.4g}"))
    print(f"\nresults in {out}/ ({_written(args)})")
    return 0


def _written(args: argparse.Namespace) -> str:
    """What a study wrote, for its last line (figures only without ``--no-figures``)."""
    return "table.md, table.csv, *.nc" + ("" if args.no_figures else ", figures")


def _study(args: argparse.Namespace) -> int:
    from kohpymc.checks import check_execution
    from kohpymc.config import StudyConfigError
    from kohpymc.progress import task_display
    from kohpymc.study import StudyStepError, run_study

    if _lists_outputs(args.study):
        return _multi_output_study(args)
    spec = _load(args)
    if spec is None:
        return 2
    kwargs = spec.run_kwargs()
    kwargs.update(_sampler_overrides(args, spec.sampling))
    kwargs.update(_execution_overrides(args, spec.execution))
    out = Path(args.out) if args.out else spec.out_dir
    try:
        _checked_options(args, spec, [out])
        try:
            check_execution(kwargs.get("workers", 1), kwargs.get("scheduler"))
        except ValueError as err:
            raise StudyConfigError(f"{spec.source}: --workers/--scheduler: {err}") from err
        _checked_build(spec, spec.formulations)
    except StudyConfigError as err:
        return _bad_input(err)
    if args.dry_run:
        return _dry_run_summary(spec, "study", [out])
    print(
        f"study {spec.source}: physics {spec.physics.name!r} "
        f"({', '.join(spec.physics.parameters)}), {spec.calibration.n} calibration and "
        f"{spec.validation.n} validation rows, formulations {', '.join(spec.formulations)}"
    )
    display = task_display(sys.stdout, quiet=args.quiet)

    def run() -> Any:
        return run_study(
            **kwargs,
            out_dir=out,
            figures=not args.no_figures,
            progress=None if args.quiet else display.write,
            display=display,
            progressbar=args.progressbar,
            fresh=args.fresh,
        )

    try:
        if spec.emulator is not None:
            kwargs["physics"] = _emulated_physics(spec, kwargs, out)
        result = run()
        if spec.emulator is not None:
            result = _posterior_rounds(spec, kwargs, out, result, run)
    except StudyStepError as err:
        print(f"error: {err}", file=sys.stderr)
        kept = ", ".join(f"{k}.nc" for k in err.result.results) if err.result else "nothing"
        print(f"finished formulations kept in {out}/: {kept} (see study.json)", file=sys.stderr)
        return 1
    except (ValueError, KeyError) as err:
        print(f"error: {spec.source}: {err}", file=sys.stderr)
        return 2
    except (RuntimeError, OSError) as err:  # OSError: e.g. the Dask scheduler is unreachable
        print(f"error: {err}", file=sys.stderr)
        return 1
    finally:
        display.close()
    print()
    print(result.summary())
    if result.failures:
        print("\nfailed: " + "; ".join(f"{k}: {v}" for k, v in result.failures.items()))
    print(f"\nresults in {out}/ ({_written(args)})")
    return 0


def _discover(args: argparse.Namespace) -> int:
    import json

    from kohpymc.config import StudyConfigError
    from kohpymc.discovery import discover

    if _lists_outputs(args.study):
        return _multi_output_discover(args)
    spec = _load(args)
    if spec is None:
        return 2
    _emulator_note(spec, "discover")
    options = _discovery_options(args, spec.sampling)
    outputs = [Path(p) for p in (args.json, args.out) if p]
    try:
        _checked_options(
            args, spec, [Path(args.out)] if args.out else [], [Path(args.json)] if args.json else []
        )
        _checked_discovery(spec)
    except StudyConfigError as err:
        return _bad_input(err)
    if args.dry_run:
        return _dry_run_summary(spec, "discover", outputs)
    try:
        report = discover(
            spec.physics,
            spec.calibration,
            spec.validation,
            tolerance=spec.tolerance,
            units=spec.units,
            **options,
        )
    except _discovery_errors() as err:
        print(f"error: {spec.source}: {err}", file=sys.stderr)
        return 2
    text = json.dumps(report.to_dict(), indent=2)
    print(text)
    _write_discovery(
        {"": (report, spec.calibration)}, text, Path(args.json) if args.json else None,
        Path(args.out) if args.out else None,
    )  # fmt: skip
    return 0


def _multi_output_discover(args: argparse.Namespace) -> int:
    """``kohpymc discover`` on a file with several outputs: discovery on each output.

    θ is borrowed from the joint calibration of all outputs
    (:func:`kohpymc.multi_output.discover_outputs`); each output's report says so
    (``"theta"``).

    The JSON report maps output -> that output's report; ``--out`` gets one folder per
    output (``<out>/<output>/report.json``, ``before.nc``, ``after.nc``, ``residuals.png``).
    """
    import json

    from kohpymc.config import StudyConfigError
    from kohpymc.multi_output import discover_outputs, load_multi_output_study

    try:
        spec = load_multi_output_study(args.study)
        if getattr(args, "workers", None) is not None or getattr(args, "scheduler", None):
            raise StudyConfigError(
                f"{spec.source}: --workers/--scheduler: a multi-output study runs its "
                "formulations in this process"
            )
        _checked_options(
            args, spec, [Path(args.out)] if args.out else [], [Path(args.json)] if args.json else []
        )
    except StudyConfigError as err:
        return _bad_input(err)
    _emulator_note(spec, "discover")
    options = _discovery_options(args, spec.sampling)
    if args.dry_run:
        print(
            f"dry run: {spec.source} is a multi-output study; discovery would run on each of "
            f"the outputs {', '.join(spec.physics.outputs)}, with θ borrowed from their joint "
            "calibration; nothing sampled, nothing written"
        )
        return 0
    try:
        reports = discover_outputs(
            spec.physics,
            spec.calibration,
            spec.validation,
            tolerance=spec.tolerance,
            units=spec.units,
            **options,
        )
    except _discovery_errors() as err:
        print(f"error: {spec.source}: {err}", file=sys.stderr)
        return 2
    text = json.dumps({k: r.to_dict() for k, r in reports.items()}, indent=2)
    print(text)
    _write_discovery(
        {k: (r, spec.calibration[k]) for k, r in reports.items()}, text,
        Path(args.json) if args.json else None, Path(args.out) if args.out else None,
    )  # fmt: skip
    return 0


def _discovery_errors() -> tuple[type[Exception], ...]:
    """Errors of a discovery run that are the input's fault (exit status 2)."""
    from kohpymc.physics import PhysicsModelError

    return (ValueError, KeyError, TypeError, NotImplementedError, PhysicsModelError)


def _discovery_options(args: argparse.Namespace, sampling: dict) -> dict:
    """Seed, progress and chain lengths of :func:`kohpymc.discover` from the file and flags."""
    merged = _sampler_overrides(args, sampling)
    return {
        "random_seed": merged.get("random_seed"),
        "progress": None if args.quiet else lambda msg: print(msg, flush=True),
        **{k: v for k, v in merged.items() if k in ("draws", "tune", "chains")},
    }


def _write_discovery(reports: dict, text: str, json_path: Path | None, out: Path | None) -> None:
    """Stage every file of the discovery reports, then move them all into place.

    ``reports`` maps a sub-folder of ``out`` (``""`` for ``out`` itself) to
    ``(report, calibration data)``; ``text`` is the JSON of the whole report.  Nothing
    is moved until every file has been written, so a failure leaves no partial output.
    """
    import shutil
    import tempfile

    targets: list[tuple[Path, Path]] = []  # (staged file, final path)
    with tempfile.TemporaryDirectory(prefix=".kohpymc-discover-") as staging:
        stage = Path(staging)
        (stage / "report.json").write_text(text + "\n")
        if json_path is not None:
            targets.append((stage / "report.json", json_path))
        if out is not None:
            for sub, (report, cal) in reports.items():
                folder = stage / sub if sub else stage
                folder.mkdir(exist_ok=True)
                names = _stage_discovery_files(report, cal, folder)
                targets += [(folder / name, (out / sub if sub else out) / name) for name in names]
        for staged, final in targets:
            final.parent.mkdir(parents=True, exist_ok=True)
            tmp = final.with_name(f".{final.name}.part")
            shutil.copyfile(staged, tmp)
            tmp.replace(final)


def _stage_discovery_files(report, cal, folder: Path) -> list[str]:
    """One report's ``report.json``, ``before.nc``, ``after.nc`` and ``residuals.png``."""
    import json

    import matplotlib.pyplot as plt
    import numpy as np

    from kohpymc.plots import plot_residuals_before_after

    if not (folder / "report.json").exists():
        (folder / "report.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    report.before.to_netcdf(str(folder / "before.nc"))
    report.after.to_netcdf(str(folder / "after.nc"))
    key = report.key_input
    others = [k for k in report.inputs if k != key]
    groups = None
    if others:
        groups = np.array([", ".join(f"{k}={cal.inputs[k][i]:g}" for k in others)
                           for i in range(cal.n)])  # fmt: skip
    fig = plot_residuals_before_after(
        cal.inputs[key],
        report.residuals["before"],
        report.residuals["after"],
        x_name=key,
        groups=groups,
        noise_sd=cal.noise_sd,
    )
    fig.savefig(folder / "residuals.png", dpi=120)
    plt.close(fig)
    return ["report.json", "before.nc", "after.nc", "residuals.png"]


def _checked_discovery(spec) -> None:
    """What :func:`kohpymc.discover` checks before sampling, run on the study file's inputs."""
    from kohpymc.candidates import DEFAULT_EXPONENTS
    from kohpymc.config import StudyConfigError
    from kohpymc.discovery.workflow import _checked_inputs
    from kohpymc.physics import PhysicsModelError

    library = {"exponents": DEFAULT_EXPONENTS, "references": None, "extra": None}
    try:
        _checked_inputs(
            spec.physics, spec.calibration, spec.validation, spec.tolerance, 0.01, None, library
        )
    except NotImplementedError as err:
        raise StudyConfigError(f"{spec.source}: [physics.backend] {err}") from err
    except (ValueError, KeyError, PhysicsModelError) as err:
        message = str(err).strip("'\"")
        raise StudyConfigError(f"{spec.source}: [data.calibration] {message}") from err


#: exit status of ``kohpymc check`` when the set-up does not recover the truth
CHECK_FAILED = 3


def _checked_check(args: argparse.Namespace, spec):
    """The check's settings and where its replicates run, as the check will resolve them.

    Command line over ``[check]`` over ``[sampling]`` (:func:`kohpymc.sbc.settings.resolve`).
    """
    from kohpymc.checks import check_execution
    from kohpymc.config import StudyConfigError
    from kohpymc.sbc.settings import resolve

    overrides = {
        "replicates": args.replicates, "formulation": args.formulation, "draws": args.draws,
        "tune": args.tune, "chains": args.chains, "seed": args.seed,
        "rank_draws": args.rank_draws,
    }  # fmt: skip
    try:
        settings = resolve(spec, overrides)
    except ValueError as err:
        message = str(err).removeprefix(f"{spec.source}: ")
        raise StudyConfigError(f"{spec.source}: [check] {message}") from err
    try:
        check_execution(args.workers, args.scheduler)
    except ValueError as err:
        raise StudyConfigError(f"{spec.source}: --workers/--scheduler: {err}") from err
    return settings


def _check(args: argparse.Namespace) -> int:
    from kohpymc.config import StudyConfigError
    from kohpymc.sbc import check_calibration

    if _lists_outputs(args.study):
        return _bad_input(
            StudyConfigError(
                f"{args.study}: [physics.output] `kohpymc check` takes one output; "
                "this file lists several (a multi-output study)"
            )
        )
    spec = _load(args)
    if spec is None:
        return 2
    _emulator_note(spec, "check")
    label = args.formulation or spec.check.formulation or "M0"
    out = Path(args.out) if args.out else Path(f"{spec.out_dir}_check_{label}")
    try:
        _checked_options(args, spec, [out])
        settings = _checked_check(args, spec)
        _checked_build(spec, {settings.formulation: spec.formulations[settings.formulation]})
    except StudyConfigError as err:
        return _bad_input(err)
    if args.dry_run:
        detail = (
            f"check of {settings.formulation}: {settings.replicates} replicate(s) of "
            f"{settings.chains} × {settings.draws} draws (tune {settings.tune}), "
            f"seed {settings.seed}"
        )
        return _dry_run_summary(spec, "check", [out], detail)
    say = None if args.quiet else (lambda msg: print(msg, flush=True))
    try:
        result = check_calibration(
            spec,
            replicates=args.replicates,
            formulation=args.formulation,
            draws=args.draws,
            tune=args.tune,
            chains=args.chains,
            seed=args.seed,
            rank_draws=args.rank_draws,
            out_dir=out,
            workers=args.workers,
            scheduler=args.scheduler,
            fresh=args.fresh,
            progress=say,
        )
    except (ValueError, KeyError, NotImplementedError) as err:
        message = str(err).strip("'\"")
        if str(spec.source) not in message:
            message = f"{spec.source}: {message}"
        print(f"error: {message}", file=sys.stderr)
        return 2
    except RuntimeError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    from kohpymc.study_files import markdown_table

    print()
    print(markdown_table(result.table))
    if result.flagged or result.failures:
        print(
            f"\n{len(result.flagged)} replicate(s) with sampler trouble and "
            f"{len(result.failures)} failed, left out (see {out}/check.json)"
        )
    print(f"\n{result.verdict}")
    print(f"\nresults in {out}/ (table.md, table.csv, ranks.nc, ranks.png, check.json)")
    return 0 if result.passed else CHECK_FAILED


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
    common.add_argument(
        "--dry-run",
        action="store_true",
        help="check the study file, its data, physics, priors and formulations; "
        "sample and write nothing",
    )
    study = sub.add_parser(
        "study", parents=[common], help="calibrate, validate and weigh formulations"
    )
    study.add_argument("study", help="study TOML file")
    study.add_argument("--out", help="output folder (default: [output] dir of the file)")
    study.add_argument("--no-figures", action="store_true", help="skip the figures")
    study.add_argument("--progressbar", action="store_true", help="PyMC's progress bar")
    study.add_argument(
        "--fresh", action="store_true", help="recompute every formulation (no reuse of --out)"
    )
    where = study.add_mutually_exclusive_group()
    where.add_argument(
        "--workers", type=int, help="formulations at once on a local Dask cluster of N processes"
    )
    where.add_argument("--scheduler", help="run on an existing Dask cluster (tcp://HOST:PORT)")
    study.set_defaults(run=_study)
    disc = sub.add_parser("discover", parents=[common], help="find, name and add a missing effect")
    disc.add_argument("study", help="study TOML file (same format as `kohpymc study`)")
    disc.add_argument("--json", help="write the JSON report here")
    disc.add_argument("--out", help="folder for report.json, before/after NetCDF, figure")
    disc.set_defaults(run=_discover)
    check = sub.add_parser(
        "check",
        parents=[common],
        help="simulation-based calibration: does this set-up recover the truth?",
        description="Exit status: 0 PASS, 3 FAIL, 2 bad input, 1 no replicate finished.",
    )
    check.add_argument("study", help="study TOML file (its [check] table sets defaults)")
    check.add_argument("--replicates", type=int, help="simulated data sets (else [check])")
    check.add_argument("--formulation", help="label of the formulation to check (default M0)")
    check.add_argument("--rank-draws", type=int, help="thinned draws a rank is among (99)")
    check.add_argument("--out", help="output folder (default: <[output] dir>_check_<label>)")
    check.add_argument("--workers", type=int, default=1, help="Dask worker processes")
    check.add_argument("--scheduler", help="address of a running Dask scheduler")
    check.add_argument("--fresh", action="store_true", help="recompute every replicate")
    check.set_defaults(run=_check)
    args = parser.parse_args(argv)
    quiet_command_line()
    return args.run(args)


def run() -> None:
    """The ``kohpymc`` command: :func:`main`, then exit at once with its status.

    Output is flushed and every file is closed by then; what is skipped is the
    interpreter's teardown of PyTensor's, Numba's and nutpie's objects, which took 2–7 s
    after a beam study on a busy 2-core machine (benchmarks/latency.py, docs/benchmarks.md).
    Library callers use :func:`main`, which returns the status.
    """
    status = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


if __name__ == "__main__":  # pragma: no cover
    run()
