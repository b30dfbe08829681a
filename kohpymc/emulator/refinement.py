"""Add simulator runs where the posterior will be, until the emulator passes its check there.

Leave-one-out over the prior box can pass an emulator that is many noise sds wrong at the
parameters that fit the data (:func:`~kohpymc.emulator.checking.check_at_data`).
:func:`refine_at_data` answers a failed check without sampling: around the emulator's best
fit ``θ̂`` it adds a small space-filling design of θ, spread over ``spread`` sds of the
linearised posterior through the emulator (:func:`local_design`), plus ``θ̂`` itself, each
θ at every distinct calibration input row; it refits, checks again, and stops when
the check passes, after ``rounds`` rounds, or when ``max_runs`` runs have been added.
:func:`refine_emulators_at_data` does the same for a simulator with several outputs and
one emulator per output (:class:`~kohpymc.emulator.at_data.EmulatorsAtData`): the check
and the local design at the outputs' joint best fit, each run giving every output.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.emulator.at_data import EmulatorsAtData
from kohpymc.emulator.checking import EmulatorCheck, check_target_at_data
from kohpymc.emulator.design import space_filling_design
from kohpymc.emulator.gp import Emulator

__all__ = [
    "Refinement",
    "design_around",
    "local_design",
    "refine_at_data",
    "refine_emulators_at_data",
]


@dataclass
class Refinement:
    """The rounds of :func:`refine_at_data` (or :func:`refine_emulators_at_data`).

    Attributes
    ----------
    target : EmulatorsAtData
        The last emulators (one per output) with their data.
    checks : list of EmulatorCheck or OutputsCheck
        The check at the data before the first round and after each round (an
        :class:`~kohpymc.emulator.checking.OutputsCheck` for several outputs).
    added : list of int
        Runs added in each round.
    stopped : str
        Why the rounds ended: ``"passed"``, ``"rounds"`` (the last round was run) or
        ``"max_runs"`` (no room left for another round).
    """

    target: EmulatorsAtData
    checks: list[Any] = field(default_factory=list)
    added: list[int] = field(default_factory=list)
    stopped: str = "passed"

    @property
    def emulators(self) -> dict[str, Emulator]:
        """Output -> its last emulator."""
        return self.target.emulators

    @property
    def emulator(self) -> Emulator:
        """The last emulator of a single-output simulator."""
        if not self.target.single:
            raise ValueError(
                f"a refinement of outputs {list(self.emulators)} has one emulator per "
                "output: see .emulators"
            )
        return self.target.first

    @property
    def passed(self) -> bool:
        """Whether the last check at the data passed."""
        return bool(self.checks[-1].fit)

    def to_dict(self) -> dict[str, Any]:
        """Per round its runs and check (``check_at_data.json``'s fields); how it ended."""
        rounds = []
        for i, check in enumerate(self.checks):
            added = self.added[i - 1] if i else 0
            rounds.append({"round": i, "added_runs": added, "check": check.to_dict()})
        return {
            "passed": self.passed,
            "stopped": self.stopped,
            "added_runs": int(sum(self.added)),
            "runs": self.target.n_runs,
            "rounds": rounds,
        }

    def summary(self) -> str:
        """One line: how many rounds and runs, and whether the check passes now."""
        n = len(self.added)
        if n == 0:
            return "passed at the first check" if self.passed else "failed (no rounds run)"
        outcome = "passes" if self.passed else "still fails"
        return (
            f"{n} round(s) added {sum(self.added)} runs at the data; the check there "
            f"{outcome} ({self.target.n_runs} runs)"
        )


def local_design(
    emulator: Emulator,
    data: CalibrationData,
    theta: dict[str, float],
    n: int,
    *,
    spread: float = 3.0,
    seed: int = 0,
) -> pd.DataFrame:
    """``n`` space-filling θ within ``spread`` linearised posterior sds of ``theta``.

    The emulator is linearised at ``theta`` in the coordinates of its unit box (ln θ
    for log-scaled parameters; :func:`~kohpymc.emulator.at_data.linearisation`,
    its own covariance added to the noise, so a poor emulator gets a wider design); a
    maximin Latin hypercube on ``[-1, 1]^p`` is mapped along the eigenvectors of that
    posterior's precision, each axis scaled by ``spread`` sds (at most the box's
    width, for a direction the data do not inform) and clipped to the box.  For several
    outputs, :func:`design_around` (their joint linearised posterior).

    Parameters
    ----------
    emulator : Emulator
    data : CalibrationData
        The calibration data.
    theta : dict
        The centre (the emulator's best fit, :attr:`EmulatorCheck.point`).
    n : int
        Number of θ points.
    spread : float
        Half-width of the design in posterior sds.
    seed : int
        Seed of the Latin hypercube.

    Returns
    -------
    pandas.DataFrame
        ``n`` rows, one column per parameter.

    Examples
    --------
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> data = beam.generate_data(seed=1)
    >>> em = emulate(beam.physics_model(), data, runs=20)
    >>> d = local_design(em, data, {"E": 200.0}, 5)
    >>> len(d), bool(d["E"].between(190.0, 210.0).all())
    (5, True)
    """
    return design_around(EmulatorsAtData.of(emulator, data), theta, n, spread=spread, seed=seed)


def design_around(
    target: EmulatorsAtData,
    theta: dict[str, float],
    n: int,
    *,
    spread: float = 3.0,
    seed: int = 0,
) -> pd.DataFrame:
    """:func:`local_design` of every output's emulator at once (their joint posterior).

    The outputs are stacked in their noise's units
    (:meth:`~kohpymc.emulator.at_data.EmulatorsAtData.whitened_linearisation`), so the
    design spreads along the linearised posterior of θ given all outputs' data.

    Examples
    --------
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> data = beam.generate_data(seed=1)
    >>> target = EmulatorsAtData.of(emulate(beam.physics_model(), data, runs=20), data)
    >>> len(design_around(target, {"E": 200.0}, 4))
    4
    """
    emulator, names = target.first, target.parameters
    cols = [emulator.columns.index(k) for k in names]
    logs, width = emulator.log_columns[cols], emulator.width[cols]
    centre = np.array([theta[k] for k in names], dtype=float)
    J, cov = target.whitened_linearisation(theta)
    Ju = J * (width * np.where(logs, centre, 1.0))  # d mean / d unit coordinate, in σ
    precision = Ju.T @ np.linalg.solve(np.eye(len(J)) + cov, Ju)
    eigenvalues, vectors = np.linalg.eigh(precision)
    with np.errstate(divide="ignore"):
        sds = np.minimum(1.0 / np.sqrt(np.maximum(eigenvalues, 0.0)), 1.0)
    box = {f"z{i}": (-1.0, 1.0) for i in range(len(names))}
    z = space_filling_design(box, n, seed=seed).to_numpy(float)
    unit = emulator.parameters_to_unit(centre)
    points = np.clip(unit + (spread * z * sds) @ vectors.T, 0.0, 1.0)
    return pd.DataFrame(emulator.parameters_from_unit(points), columns=names)


def refine_at_data(
    emulator: Emulator,
    data: CalibrationData,
    *,
    rounds: int = 2,
    new_runs: int | None = None,
    max_runs: int | None = None,
    first: EmulatorCheck | None = None,
    spread: float = 3.0,
    cache: str | Path | None = None,
    seed: int = 0,
    workers: int = 1,
    scheduler: Any = None,
) -> Refinement:
    """Check the emulator at the data; while it fails, add runs around its best fit.

    Each round runs θ̂ (the check's own point) and ``max(p + 1, round(new_runs / m))``
    θ of :func:`local_design` at the ``m`` distinct calibration input rows (a check that
    nearly passed — least-squares θ moved ≤ 1 sd, posterior sd widened ≤ 1.5×, errors
    below the simulator's misfit — gets θ̂ and one local θ: the slow-simulator study's
    round of 100 runs became 40, its emulator's M0 gradient 1.2–1.4× the 150-run one's
    instead of 1.8–2.0×, the posterior within 0.05 direct sds either way), refits
    (:func:`~kohpymc.emulator.sequential.refit`) and checks again.  No warning is
    issued; the caller warns on a failed last check
    (:func:`~kohpymc.emulator.checking.warn_at_data`).

    Parameters
    ----------
    emulator : Emulator
    data : CalibrationData
    rounds : int
        Most rounds (0: just the check).
    new_runs : int, optional
        About how many runs a round adds (default half the emulator's runs).
    max_runs : int, optional
        Most runs added over all rounds (default: room for every round); a round that
        would pass it runs fewer θ, or none.
    first : EmulatorCheck, optional
        The check of ``emulator`` already made (else made here).
    spread : float
        Half-width of the local designs in linearised posterior sds.
    cache, seed, workers, scheduler :
        As for :func:`~kohpymc.emulator.emulate`; every run is cached.

    Returns
    -------
    Refinement

    Examples
    --------
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> result = refine_at_data(emulate(physics, data, runs=12), data, max_runs=100)
    >>> result.checks[0].fit, result.passed, result.added  # 3 θ at the 20 data rows
    (False, True, [60])
    """
    return refine_emulators_at_data(
        EmulatorsAtData.of(emulator, data), rounds=rounds, new_runs=new_runs,
        max_runs=max_runs, first=first, spread=spread, cache=cache, seed=seed,
        workers=workers, scheduler=scheduler,
    )  # fmt: skip


def refine_emulators_at_data(
    target: EmulatorsAtData,
    *,
    rounds: int = 2,
    new_runs: int | None = None,
    max_runs: int | None = None,
    first: Any = None,
    spread: float = 3.0,
    cache: str | Path | None = None,
    seed: int = 0,
    workers: int = 1,
    scheduler: Any = None,
) -> Refinement:
    """:func:`refine_at_data` for one emulator per output of one simulator.

    The check is :func:`~kohpymc.emulator.checking.check_emulators_at_data` (the
    outputs' joint best fit ``θ̂``; for one output :func:`check_at_data`'s), the θ
    around it come from :func:`design_around` (the joint linearised posterior), each θ
    runs at the distinct calibration rows of all outputs (one simulator call gives every
    output; cached) and every output's emulator is refitted to the new runs.

    Parameters
    ----------
    target : EmulatorsAtData
        The simulator, its emulators and their data.
    rounds, new_runs, max_runs, spread, cache, seed, workers, scheduler :
        As for :func:`refine_at_data` (``m`` counts the distinct rows of all outputs and
        ``target.predict_rows``, where each θ runs as well).
    first : EmulatorCheck or OutputsCheck, optional
        The check of the emulators already made (else made here).

    Returns
    -------
    Refinement

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> from kohpymc.multi_output import emulate_outputs
    >>> physics, data = bm.physics_model(), bm.generate_data()
    >>> target = EmulatorsAtData.of_outputs(physics, emulate_outputs(physics, data, runs=20),
    ...                                     data)
    >>> result = refine_emulators_at_data(target, rounds=1)
    >>> result.checks[0].fit, len(result.added), sorted(result.emulators)
    (False, 1, ['strain', 'u'])
    """
    if rounds < 0:
        raise ValueError(f"rounds must be >= 0, got {rounds}")
    where = {"cache": cache, "workers": workers, "scheduler": scheduler}
    check = first or check_target_at_data(target, **where)
    result = Refinement(target, [check])
    m = len(target.design_rows())
    per_round = new_runs if new_runs is not None else max(1, target.n_runs // 2)
    n_local = max(len(target.parameters) + 1, int(round(per_round / m)))
    budget = max_runs if max_runs is not None else rounds * (n_local + 1) * m
    for round_ in range(1, rounds + 1):
        if check.fit:
            return result
        room = (budget - sum(result.added)) // m - 1  # θ̂ takes one of them
        if room < 1:
            result.stopped = "max_runs"
            return result
        n = min(NEAR_LOCAL if _nearly_passed(check) else n_local, room)
        thetas = pd.DataFrame([check.point])
        if n > 0:
            local = design_around(result.target, check.point, n, spread=spread, seed=seed + round_)
            thetas = pd.concat([thetas, local], ignore_index=True)
        runs = result.target.run(result.target.design(thetas), **where)
        result.target = result.target.refit(runs, seed=seed)
        result.added.append(len(runs.points))
        check = check_target_at_data(result.target, **where)
        result.checks.append(check)
    result.stopped = "passed" if check.fit else "rounds"
    return result


#: a failed check this close to passing (least-squares θ moved ≤ 1 sd, posterior sd widened
#: ≤ 1.5×, errors below the simulator's misfit) gets θ̂ and :data:`NEAR_LOCAL` local θ
NEAR_SHIFT, NEAR_WIDENING = 1.0, 1.5
NEAR_LOCAL = 1


def _nearly_passed(check: Any) -> bool:
    """Whether the check nearly passed (then a round needs few new θ).

    Every output's error is below the simulator's misfit, the least-squares θ moved by
    at most :data:`NEAR_SHIFT` sds and the posterior sd widened by at most
    :data:`NEAR_WIDENING`.
    """
    outputs = getattr(check, "checks", {"": check})
    if any(c.misfit is None or c.rmse > c.misfit for c in outputs.values()):
        return False
    shift = max((abs(v) for v in (check.shift or {}).values()), default=0.0)
    widening = max((check.widening or {}).values(), default=1.0)
    return shift <= NEAR_SHIFT and widening <= NEAR_WIDENING
