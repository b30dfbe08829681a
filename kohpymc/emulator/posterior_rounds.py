"""Runs added where a formulation's posterior lies when the emulator is unfit there.

After a study's calibrations through the emulator, every formulation's posterior mean
has been scored against one simulator run
(:func:`~kohpymc.emulator.posterior_check.check_at_posterior`, in
``idata.attrs["physics_problems"]``).  For each formulation that failed,
:func:`refine_at_posteriors` runs the simulator at its posterior mean and at
``2p + 1`` (or more) of its posterior draws, on the calibration and validation rows,
and refits the emulator to all the runs; the study then calibrates again through it
(``[emulator] refine_at_posterior`` rounds, default 1).  ``refine_at_posterior.json``
records each round: the formulations, their problems, the runs added, and how far each
formulation's posterior mean then moved, in its sds.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from kohpymc.data import CalibrationData
from kohpymc.emulator.at_data import EmulatorsAtData
from kohpymc.study_files import write_atomic

__all__ = ["POSTERIOR_RECORD", "PosteriorRounds", "refine_at_posteriors", "posterior_moves"]

#: the record of the rounds at the posteriors (in ``<output>/emulator``)
POSTERIOR_RECORD = "refine_at_posterior.json"


@dataclass
class PosteriorRounds:
    """The rounds at the posteriors of a study, as recorded.

    Attributes
    ----------
    key : str
        What the emulator's rounds depend on (``rounds.json``'s key): a record under
        another key is not this study's.
    rounds : list of dict
        One per round: ``unfit`` (label -> problems), ``thetas``, ``runs_added``,
        ``runs`` (after the round), and after the next calibrations ``moved`` (label ->
        parameter -> move of the posterior mean in its sds) and ``still_unfit``.

    Examples
    --------
    >>> record = PosteriorRounds("k")
    >>> record.done, PosteriorRounds.read(Path("/nonexistent"), "k").done
    (0, 0)
    """

    key: str
    rounds: list[dict[str, Any]] = field(default_factory=list)

    @property
    def done(self) -> int:
        """How many rounds ran."""
        return len(self.rounds)

    @classmethod
    def read(cls, folder: Path, key: str) -> PosteriorRounds:
        """The record in ``folder`` when written under ``key``; else an empty one."""
        try:
            record = json.loads((folder / POSTERIOR_RECORD).read_text())
        except (OSError, ValueError):
            return cls(key)
        if not isinstance(record, dict) or record.get("key") != key:
            return cls(key)
        return cls(key, list(record.get("rounds", [])))

    def write(self, folder: Path) -> None:
        """``refine_at_posterior.json``, written under a temporary name and renamed."""
        text = json.dumps({"key": self.key, "rounds": self.rounds}, indent=2)
        write_atomic(folder / POSTERIOR_RECORD, lambda tmp: tmp.write_text(text))


def refine_at_posteriors(
    emulator: Any,
    calibration: CalibrationData,
    posteriors: Mapping[str, Any],
    *,
    validation: CalibrationData | None = None,
    new_runs: int | None = None,
    cache: str | Path | None = None,
    seed: int = 0,
    workers: int = 1,
    scheduler: Any = None,
) -> tuple[Any, pd.DataFrame]:
    """The emulator refitted with runs at each posterior's mean and draws.

    For each posterior, the simulator runs at its mean and at ``max(2p + 1, new_runs /
    m)`` of its draws (``p`` parameters, ``m`` distinct rows; picked at random with
    ``seed``), each θ on the calibration rows and the ``validation`` rows (one simulator
    call per θ; cached in ``cache``).

    Parameters
    ----------
    emulator : Emulator
        The emulator to refine (its ``physics`` is the simulator).
    calibration : CalibrationData
        The calibration data.
    posteriors : mapping of str to Dataset or InferenceData
        Label -> a posterior (with a variable per physics parameter) whose region the
        emulator is unfit in.
    validation : CalibrationData, optional
        Rows where the θ run as well (the study's predictions rest on them).
    new_runs : int, optional
        About how many runs (points) to add per posterior; default half the emulator's.
    cache, seed, workers, scheduler :
        As for :func:`~kohpymc.emulator.runs.run_design`.

    Returns
    -------
    (Emulator, pandas.DataFrame)
        The refitted emulator and the θ that ran (a ``posterior`` column names whose).

    Examples
    --------
    >>> import xarray as xr
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> em = emulate(physics, data, runs=10)
    >>> post = xr.Dataset({"E": (("chain", "draw"), [[195.0, 200.0, 205.0, 210.0]])})
    >>> refined, thetas = refine_at_posteriors(em, data, {"M1": post}, new_runs=10)
    >>> len(thetas), refined.n_runs == 10 + len(thetas) * data.n
    (4, True)
    """
    target = EmulatorsAtData.of(emulator, calibration).also_at(validation)
    rows = len(target.design_rows())
    per_posterior = new_runs if new_runs is not None else max(1, emulator.n_runs // 2)
    n_draws = max(2 * len(target.parameters) + 1, int(round(per_posterior / rows)))
    rng = np.random.default_rng(seed)
    thetas = pd.concat(
        [_thetas(post, target.parameters, n_draws, rng).assign(posterior=label)
         for label, post in posteriors.items()],
        ignore_index=True,
    )  # fmt: skip
    runs = target.run(
        target.design(thetas[target.parameters]), cache=cache, workers=workers,
        scheduler=scheduler,
    )  # fmt: skip
    refined = target.refit(runs, seed=seed)
    return refined.first, thetas


def _thetas(posterior: Any, names: list[str], n_draws: int, rng: np.random.Generator):
    """The posterior mean and ``n_draws`` of its draws (all of them when fewer)."""
    post = getattr(posterior, "posterior", posterior)
    draws = np.column_stack([np.asarray(post[k], float).reshape(-1) for k in names])
    picked = draws[rng.choice(len(draws), size=min(n_draws, len(draws)), replace=False)]
    mean = draws.mean(axis=0, keepdims=True)
    return pd.DataFrame(np.vstack([mean, picked]), columns=names)


def posterior_moves(
    before: Mapping[str, Any], after: Mapping[str, Any], names: list[str]
) -> dict[str, dict[str, float]]:
    """Label -> parameter -> the move of its posterior mean, in the later posterior's sds.

    Examples
    --------
    >>> import xarray as xr
    >>> a = xr.Dataset({"E": ("draw", [1.0, 3.0])})
    >>> b = xr.Dataset({"E": ("draw", [2.0, 4.0])})
    >>> posterior_moves({"M0": a}, {"M0": b}, ["E"])
    {'M0': {'E': 1.0}}
    """
    moves = {}
    for label in before.keys() & after.keys():
        old = getattr(before[label], "posterior", before[label])
        new = getattr(after[label], "posterior", after[label])
        moves[label] = {
            k: float((new[k].mean() - old[k].mean()) / new[k].std()) if new[k].std() > 0 else 0.0
            for k in names
        }
    return moves
