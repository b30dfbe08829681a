r"""Emulating a simulator with several outputs: one design, one run, a GP per output.

:func:`emulate_outputs` fills the box of the calibration inputs (their range over every
output's rows) × the prior box of θ with one space-filling design, runs the simulator
once per design point for all its outputs (:func:`~kohpymc.emulator.run_design`: tasks,
cached on disk, failures recorded) and fits one :class:`~kohpymc.emulator.Emulator` to
each output's runs.  :func:`emulated_outputs` turns them into one
:class:`~kohpymc.multi_output.MultiOutputPhysics` whose outputs are
:class:`~kohpymc.emulator.EmulatedPhysics`, so each output's emulator uncertainty
enters that output's likelihood exactly as for a single output:

.. math::

    y_k \sim N\big(\hat\eta_k(X_k, \theta) + \delta_k,\;
    \Sigma_{\eta,k}(\theta) + \Sigma_{\delta,k} + \sigma_k^2 I\big).

The outputs' emulators are fitted separately, so their errors are independent across
outputs (as the outputs' discrepancies are by default).

:func:`study_outputs_physics` is the ``[emulator]`` table of a multi-output study file
(:mod:`kohpymc.multi_output.config`): the runs are cached in ``<output>/emulator/runs/``
(a resumed study reads them and runs nothing), and each output's check (closed-form
leave-one-out: standardised errors, coverage of the 90 % bands), figure, hyperparameters
and runs go to ``<output>/emulator/<k>/`` (``check.json``, ``check.png``,
``emulator.json``, ``runs.csv``) as a single-output study writes them to
``<output>/emulator/``; the predicted posterior widening of the check is that of the
output's own data alone (linearised).  The check at the data runs the simulator once at the
emulators' joint best fit and scores every output there
(:func:`~kohpymc.emulator.check_emulators_at_data`, ``<output>/emulator/check_at_data.json``);
while it fails, ``refine_at_data`` rounds add runs around that fit, each giving every output
(:func:`~kohpymc.emulator.refine_emulators_at_data`, ``refine_at_data.json``), and
``rounds.json`` lets a rerun refit the final emulators from the cache.  Sequential design
rounds are for single-output studies only.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np

from kohpymc.emulator.at_data import EmulatorsAtData
from kohpymc.emulator.design import DesignMethod, design_box, space_filling_design
from kohpymc.emulator.gp import Emulator
from kohpymc.emulator.runs import run_design
from kohpymc.emulator.sequential import fit_emulator
from kohpymc.emulator.study import (
    EmulatorSettings,
    rounds_key,
    study_emulators,
    warn_if_extrapolating,
    write_emulator,
    write_settings,
)
from kohpymc.multi_output.data import MultiOutputData
from kohpymc.multi_output.physics import MultiOutputPhysics

__all__ = [
    "emulate_outputs",
    "emulated_outputs",
    "output_design_box",
    "study_outputs_physics",
]


def output_design_box(
    physics: MultiOutputPhysics,
    data: MultiOutputData,
    *,
    bounds: Mapping[str, tuple[float, float]] | None = None,
) -> dict[str, tuple[float, float]]:
    """The design box: each input's range over every output's rows, then θ's prior box.

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> box = output_design_box(bm.physics_model(), bm.generate_data((2.0, 6.0)))
    >>> box["P"], box["E"]
    ((2.0, 6.0), (50.0, 300.0))
    """
    ranges = {}
    for name in physics.inputs:
        values = np.concatenate(
            [np.asarray(data[k].inputs[name], dtype=float) for k in data.outputs]
        )
        ranges[name] = (float(values.min()), float(values.max()))
    first = physics.output(physics.outputs[0])  # every output has the same priors
    return design_box(first, inputs=ranges, bounds=bounds)


def emulate_outputs(
    physics: MultiOutputPhysics,
    data: MultiOutputData,
    *,
    runs: int = 100,
    design: DesignMethod = "maximin-lhs",
    kernel: Literal["matern52", "se"] = "matern52",
    bounds: Mapping[str, tuple[float, float]] | None = None,
    cache: str | Path | None = None,
    seed: int = 0,
    workers: int = 1,
    scheduler: Any = None,
    log_output: bool | Literal["auto"] = "auto",
) -> dict[str, Emulator]:
    """One design, one simulator run per point for every output, one emulator per output.

    Parameters
    ----------
    physics : MultiOutputPhysics
        The simulator: one call returns every output.
    data : MultiOutputData
        Calibration data (their input ranges, over all outputs, bound the design).
    runs, design, kernel, bounds, cache, seed, workers, scheduler, log_output :
        As for :func:`kohpymc.emulator.emulate`; with ``log_output="auto"`` each
        output's scale is chosen for that output (:func:`kohpymc.emulator.fit_emulator`).

    Returns
    -------
    dict of str to Emulator
        Output -> its emulator, fitted to the same runs.

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> emulators = emulate_outputs(bm.physics_model(), bm.generate_data(), runs=20)
    >>> {k: em.n_runs for k, em in emulators.items()}
    {'u': 20, 'strain': 20}
    """
    box = output_design_box(physics, data, bounds=bounds)
    points = space_filling_design(box, runs, method=design, seed=seed)
    done = run_design(physics, points, cache=cache, workers=workers, scheduler=scheduler)
    return {
        k: fit_emulator(
            done.output(k),
            physics.output(k),
            box=box,
            kernel=kernel,
            seed=seed,
            log_output=log_output,
        )
        for k in physics.outputs
    }


def emulated_outputs(
    physics: MultiOutputPhysics,
    emulators: Mapping[str, Emulator],
    *,
    covariance: Literal["full", "diagonal"] = "full",
) -> MultiOutputPhysics:
    """The emulators as one multi-output physics model (each with its own uncertainty).

    Parameters
    ----------
    physics : MultiOutputPhysics
        The simulator (names the model: ``"<name> (emulated)"``).
    emulators : mapping output -> Emulator
        From :func:`emulate_outputs`.
    covariance : {"full", "diagonal"}
        As for :meth:`kohpymc.emulator.Emulator.physics_model`.

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> physics = bm.physics_model()
    >>> emulated = emulated_outputs(physics, emulate_outputs(physics, bm.generate_data(),
    ...                                                      runs=20))
    >>> emulated.name, emulated.output("u").name
    ('beam_outputs (emulated)', 'beam_outputs[u] (emulated)')
    """
    models = {k: em.physics_model(covariance=covariance) for k, em in emulators.items()}
    return MultiOutputPhysics.from_models(models, name=f"{physics.name} (emulated)")


def study_outputs_physics(
    settings: EmulatorSettings,
    physics: MultiOutputPhysics,
    calibration: MultiOutputData,
    out_dir: str | Path,
    *,
    workers: int = 1,
    scheduler: Any = None,
    validation: MultiOutputData | None = None,
) -> MultiOutputPhysics:
    """Build (or rebuild from cached runs) a multi-output study's emulators as physics.

    As :func:`kohpymc.emulator.study.study_physics` for one output
    (:func:`~kohpymc.emulator.study.study_emulators`): the checks over the design
    (``emulator/<output>/check.json``), the check at the data over all outputs at once
    (``emulator/check_at_data.json``, :func:`~kohpymc.emulator.check_emulators_at_data`),
    the refinement rounds at the data while it fails (``refine_at_data``,
    ``emulator/refine_at_data.json``; each new run gives every output) and
    ``emulator/rounds.json``, from which a rerun with the same settings, simulator and
    data refits the final emulators without a simulator call.

    Parameters
    ----------
    settings : EmulatorSettings
        The ``[emulator]`` table (``sequential`` must be 0).
    physics, calibration :
        The study's simulator and calibration data.
    out_dir : path
        The study's output folder (``emulator/`` is written inside).
    workers, scheduler :
        Where the simulator runs go.
    validation : MultiOutputData, optional
        An ``EmulatorWarning`` names each output's validation inputs outside the box;
        the refinement rounds run each θ at the validation rows too.

    Returns
    -------
    MultiOutputPhysics

    Raises
    ------
    ValueError
        ``settings.sequential > 0``.

    Examples
    --------
    >>> import tempfile
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> folder = Path(tempfile.mkdtemp())
    >>> settings = EmulatorSettings(runs=20, refine_at_data=0)
    >>> emulated = study_outputs_physics(settings, bm.physics_model(), bm.generate_data(),
    ...                                  folder)
    >>> sorted(p.name for p in (folder / "emulator" / "u").iterdir())
    ['check.json', 'check.png', 'emulator.json', 'runs.csv']
    """
    if settings.sequential > 0:
        raise ValueError(
            "sequential design rounds are for single-output studies; a multi-output "
            "emulator takes runs = N (sequential = 0)"
        )
    folder = Path(out_dir) / "emulator"
    key = (
        rounds_key(settings, physics, calibration, validation=validation)
        if settings.refine_at_data > 0
        else ""
    )

    def first() -> EmulatorsAtData:
        emulators = emulate_outputs(
            physics, calibration, cache=folder / "runs", workers=workers, scheduler=scheduler,
            **settings.design_options(),
        )  # fmt: skip
        return EmulatorsAtData.of_outputs(physics, emulators, calibration).also_at(validation)

    emulators = study_emulators(
        settings, physics, folder, first, key=key, workers=workers, scheduler=scheduler
    )
    write_settings(folder, settings)
    for name, emulator in emulators.items():
        (folder / name).mkdir(parents=True, exist_ok=True)
        write_emulator(folder / name, emulator)
        if validation is not None and name in validation.outputs:
            warn_if_extrapolating(emulator, validation[name], "validation")
    return emulated_outputs(physics, emulators, covariance=settings.covariance)  # type: ignore[arg-type]
