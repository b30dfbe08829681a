"""Is the emulator fit for calibration?  Leave-one-out or held-out runs, scored.

:func:`check_emulator` predicts every run left out of the fit (closed-form leave-one-out
of the GP, :meth:`~kohpymc.emulator.gp.Emulator.leave_one_out`) or runs it was not
fitted to (``held_out=``) and reports:

* standardised errors ``(simulated - mean) / sd`` (about N(0, 1) for a calibrated GP);
* the coverage of the central ``level`` (90 %) predictive bands;
* the RMSE relative to the sd of the simulated outputs;

and issues an :class:`EmulatorWarning` when the emulator is not fit for calibration: a
coverage far below ``level`` (its bands are too narrow, so the calibration would be
overconfident), far above it (too wide: a posterior wider than needed), or a large
relative error.  Given the calibration data (``data=``), it also estimates how much wider
the posterior of θ will be through the emulator than through the simulator: an emulator
good to 1 % of its outputs' spread may still be off by a fraction of the noise sd where
the data are, and its errors are correlated across the data's rows, so they do not
average out as noise does (:func:`posterior_widening`).  :meth:`EmulatorCheck.figure`
draws predicted against simulated with
the bands, and the histogram of the standardised errors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from kohpymc.data import CalibrationData
from kohpymc.emulator.at_data import SINGLE, EmulatorsAtData, linearisation
from kohpymc.emulator.gp import Emulator, EmulatorWarning
from kohpymc.emulator.runs import SimulatorRuns
from kohpymc.warning_filters import warn_user

__all__ = [
    "EmulatorCheck",
    "EmulatorWarning",
    "OutputsCheck",
    "check_at_data",
    "check_emulator",
    "check_emulators_at_data",
    "check_target_at_data",
    "coverage_bounds",
    "linearisation",
    "noise_sd_shift",
    "posterior_widening",
    "warn_at_data",
]

#: largest move of an unknown noise sd's best fit by the emulator, in its posterior sds (a
#: nuisance parameter: half an sd changes predictive bands by ~σ/(2√(2n)))
MAX_NOISE_SHIFT = 0.5

#: largest move of θ (posterior sds) at which the noise sd's move is still judged
_LINEAR_SHIFT = 2.0

#: largest widening of a parameter's (linearised) posterior sd that the emulator's own
#: uncertainty may cause, over the design and at the data
MAX_WIDENING = 1.25


@dataclass
class EmulatorCheck:
    """Scores of an emulator against runs it did not see.

    Attributes
    ----------
    kind : str
        ``"leave-one-out"`` or ``"held-out"``.
    simulated, mean, sd : numpy.ndarray
        Simulator outputs, predictive means and sds (of a new simulator output).
    level : float
        Nominal coverage of the bands.
    problems : list of str
        Why the emulator is not fit for calibration (empty when it is).
    widening : dict or None
        Parameter -> posterior sd through the emulator over that through the simulator,
        linearised at the least-squares θ (with ``check_emulator(..., data=)``).
    point : dict
        The parameters of a check at the data (:func:`check_at_data`), else empty.
    misfit : float or None
        For a check at the data: the simulator's own rms misfit to the data at ``point``.
    shift : dict or None
        For a check at the data: parameter -> how far the emulator's error moves the
        least-squares θ, in linearised posterior sds (:func:`check_at_data`).
    noise_shift : float or None
        For a check at the data without a known noise sd: how far the emulator's mean
        and ``Σ_η`` move the noise sd's best fit at ``point``, in its posterior sds
        (negative: ``Σ_η`` takes up part of the noise; :func:`noise_sd_shift`).

    Examples
    --------
    >>> from kohpymc.emulator import Emulator, design_box, run_design, space_filling_design
    >>> from kohpymc.examples import beam
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 30))
    >>> check = check_emulator(Emulator(runs, physics), warn=False)
    >>> check.kind, check.relative_rmse < 0.1, check.fit
    ('leave-one-out', True, True)
    """

    kind: str
    simulated: np.ndarray
    mean: np.ndarray
    sd: np.ndarray
    level: float = 0.9
    problems: list[str] = field(default_factory=list)
    widening: dict[str, float] | None = None
    point: dict[str, float] = field(default_factory=dict)
    misfit: float | None = None
    shift: dict[str, float] | None = None
    noise_shift: float | None = None

    @property
    def standardized_errors(self) -> np.ndarray:
        """``(simulated - mean) / sd`` per run."""
        return (self.simulated - self.mean) / self.sd

    @property
    def coverage(self) -> float:
        """Fraction of runs inside their central ``level`` predictive band."""
        half = stats.norm.ppf(0.5 + self.level / 2)
        return float(np.mean(np.abs(self.standardized_errors) <= half))

    @property
    def rmse(self) -> float:
        """Root-mean-square error of the predictive means."""
        return float(np.sqrt(np.mean((self.simulated - self.mean) ** 2)))

    @property
    def relative_rmse(self) -> float:
        """RMSE over the sd of the simulated outputs."""
        spread = float(np.std(self.simulated))
        return self.rmse / spread if spread > 0 else float("inf")

    @property
    def fit(self) -> bool:
        """No problems found."""
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        """The scores as plain values (for a JSON file)."""
        return {
            "kind": self.kind,
            "runs": int(self.simulated.size),
            "level": self.level,
            "coverage": self.coverage,
            "rmse": self.rmse,
            "relative_rmse": self.relative_rmse,
            "mean_standardized_error": float(np.mean(self.standardized_errors)),
            "sd_standardized_error": float(np.std(self.standardized_errors)),
            "widening": self.widening,
            "problems": list(self.problems),
            **({"point": dict(self.point)} if self.point else {}),
            **({"misfit": self.misfit} if self.misfit is not None else {}),
            **({"shift": dict(self.shift)} if self.shift is not None else {}),
            **({"noise_shift": self.noise_shift} if self.noise_shift is not None else {}),
        }

    def figure(self) -> Any:
        """Predicted vs simulated with ``level`` bands, and the standardised errors.

        Returns
        -------
        matplotlib.figure.Figure

        Examples
        --------
        >>> import numpy as np
        >>> check = EmulatorCheck("held-out", np.array([1.0, 2.0]), np.array([1.1, 1.9]),
        ...                       np.array([0.1, 0.1]))
        >>> len(check.figure().axes)
        2
        """
        import matplotlib.pyplot as plt

        half = stats.norm.ppf(0.5 + self.level / 2)
        fig, (ax, hist) = plt.subplots(1, 2, figsize=(9, 4))
        order = np.argsort(self.simulated)
        inside = np.abs(self.standardized_errors) <= half
        ax.errorbar(
            self.simulated[order],
            self.mean[order],
            yerr=half * self.sd[order],
            fmt="none",
            ecolor="0.6",
            lw=1,
            label=f"{self.level:.0%} band",
        )
        ax.plot(self.simulated[inside], self.mean[inside], "o", ms=3, label="covered")
        ax.plot(self.simulated[~inside], self.mean[~inside], "x", color="C3", label="missed")
        lims = [float(np.min(self.simulated)), float(np.max(self.simulated))]
        ax.plot(lims, lims, "k--", lw=0.8)
        ax.set_xlabel("simulated")
        ax.set_ylabel("emulator prediction")
        ax.set_title(
            f"{self.kind}: coverage {self.coverage:.2f}, rel. RMSE {self.relative_rmse:.3f}"
        )
        ax.legend(fontsize="small")
        z = self.standardized_errors
        hist.hist(z, bins=max(5, min(30, z.size // 4)), density=True, color="C0", alpha=0.6)
        grid = np.linspace(min(-4.0, float(z.min())), max(4.0, float(z.max())), 200)
        hist.plot(grid, stats.norm.pdf(grid), "k-", lw=1, label="N(0, 1)")
        hist.set_xlabel("standardised error")
        hist.legend(fontsize="small")
        fig.tight_layout()
        return fig


#: the tail probability, each side, of a band coverage called inconsistent with its level
#: (that of three normal sds)
COVERAGE_TAIL = float(stats.norm.sf(3.0))


def coverage_bounds(level: float, n: int, tolerance: float | None = None) -> tuple[float, float]:
    """The band coverages of ``n`` independent values consistent with ``level``.

    By default the exact binomial bounds: a count of covered values below ``low · n``
    (above ``high · n``) has probability at most :data:`COVERAGE_TAIL` (three normal sds)
    when each value is covered with probability ``level``; and at least 0.05 from
    ``level``.  The normal approximation ``level ± 3 sqrt(level (1 - level) / n)`` used
    before flagged 5 of 9 covered values, which happens to calibrated bands in 0.8 % of
    samples.  ``n`` counts *independent* values: the grid values of one held-out curve
    share its component weights' errors, so a functional emulator's check counts
    curves (84 grid values of 4 curves, all covered: as 84 values ``0.9⁸⁴ = 1e-4``, a
    "too wide" alarm on an emulator good to 6e-5 of the outputs' sd; as 4 curves
    ``0.9⁴ = 0.66``).  With ``tolerance``: ``level ± tolerance``.

    Examples
    --------
    >>> [round(b, 3) for b in coverage_bounds(0.9, 100)]
    [0.8, 0.98]
    >>> coverage_bounds(0.9, 4)  # four values cannot show too-wide bands
    (0.25, 1.0)
    """
    if n < 1:
        raise ValueError(f"coverage_bounds: n must be >= 1, got {n}")
    if tolerance is not None:
        return level - tolerance, level + tolerance
    low = float(stats.binom.ppf(COVERAGE_TAIL, n, level)) / n
    high = float(stats.binom.isf(COVERAGE_TAIL, n, level)) / n
    return min(low, level - 0.05), max(high, level + 0.05)


def fit_problems(
    kind: str,
    coverage: float,
    relative_rmse: float,
    n: int,
    *,
    level: float = 0.9,
    coverage_tolerance: float | None = None,
    max_relative_rmse: float = 0.1,
) -> list[str]:
    """What makes an emulator unfit, from its scores on ``n`` values it did not see.

    The coverage of the ``level`` bands must lie within :func:`coverage_bounds` (``n``
    the number of independent values, ``coverage_tolerance`` its tolerance), and the
    RMSE be at most ``max_relative_rmse`` of the values' sd.

    Examples
    --------
    >>> fit_problems("held-out", 0.78, 0.05, 930)  # doctest: +ELLIPSIS
    ["held-out coverage of the 90% bands is 0.78 (< 0.85): ... overconfident"]
    """
    low, high = coverage_bounds(level, n, coverage_tolerance)
    problems = []
    if coverage < low:
        problems.append(
            f"{kind} coverage of the {level:.0%} bands is {coverage:.2f} (< "
            f"{low:.2f}): the emulator's variance is too small, a calibration "
            "through it would be overconfident"
        )
    elif coverage > high:
        problems.append(
            f"{kind} coverage of the {level:.0%} bands is {coverage:.2f} (> "
            f"{high:.2f}): the emulator's variance is too large, the posterior "
            "would be wider than needed"
        )
    if relative_rmse > max_relative_rmse:
        problems.append(
            f"{kind} RMSE is {relative_rmse:.3f} of the outputs' sd (> "
            f"{max_relative_rmse}): add runs (see kohpymc.emulator.sequential_design)"
        )
    return problems


def check_emulator(
    emulator: Emulator,
    held_out: SimulatorRuns | None = None,
    *,
    level: float = 0.9,
    coverage_tolerance: float | None = None,
    max_relative_rmse: float = 0.1,
    data: CalibrationData | None = None,
    max_widening: float = MAX_WIDENING,
    warn: bool = True,
) -> EmulatorCheck:
    """Score an emulator on runs it did not see and warn when it is not fit.

    Parameters
    ----------
    emulator : Emulator
        The fitted emulator.
    held_out : SimulatorRuns, optional
        Runs not used in the fit; without them, closed-form leave-one-out of the fit's
        own runs (hyperparameters kept fixed).
    level : float
        Nominal coverage of the bands (0.9).
    coverage_tolerance : float, optional
        Allowed distance of the coverage from ``level``; default the binomial bounds of
        :func:`coverage_bounds`.
    max_relative_rmse : float
        Largest RMSE relative to the sd of the simulated outputs.
    data : CalibrationData, optional
        The calibration data: :attr:`EmulatorCheck.widening` from
        :func:`posterior_widening`.
    max_widening : float
        Largest allowed widening of a parameter's posterior sd (1.25).
    warn : bool
        Issue an :class:`EmulatorWarning` listing the problems.

    Returns
    -------
    EmulatorCheck

    Examples
    --------
    See :class:`EmulatorCheck`.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if held_out is None:
        mean, var = emulator.leave_one_out()
        simulated, kind = emulator.runs.y, "leave-one-out"
    else:
        if len(held_out.y) == 0:
            raise ValueError("check_emulator: held_out has no successful runs")
        mean, var = emulator.predict_matrix(held_out.X)
        simulated, kind = held_out.y, "held-out"
    check = EmulatorCheck(kind, np.asarray(simulated, float), mean, np.sqrt(var), level)
    check.problems += fit_problems(
        kind, check.coverage, check.relative_rmse, simulated.size, level=level,
        coverage_tolerance=coverage_tolerance, max_relative_rmse=max_relative_rmse,
    )  # fmt: skip
    if data is not None:
        check.widening = posterior_widening(emulator, data)
        wide = {k: v for k, v in check.widening.items() if v > max_widening}
        if wide:
            named = ", ".join(f"{k} {v:.2g}×" for k, v in wide.items())
            check.problems.append(
                f"its uncertainty at the calibration data makes the posterior sd wider than "
                f"the simulator's ({named}; > {max_widening}×, linearised at the "
                "least-squares θ): add runs (more `runs`, or sequential rounds)"
            )
    if warn and check.problems:
        warn_user(
            f"emulator of {emulator.physics.name!r} ({emulator.n_runs} runs) is not fit for "
            "calibration: " + "; ".join(check.problems),
            EmulatorWarning,
        )
    return check


def posterior_widening(emulator: Emulator, data: CalibrationData) -> dict[str, float]:
    """Posterior sd of each θ through the emulator over that through the simulator.

    Linearised at the least-squares θ̂ through the emulator's mean (as
    :func:`check_at_data`'s), with a flat prior:
    ``J`` the emulator mean's Jacobian at the data's inputs (the emulated physics'
    finite differences), the
    posterior covariance ``(Jᵀ Σ⁻¹ J)⁻¹`` with ``Σ = σ² I`` (simulator) and
    ``Σ = σ² I + Σ_η(θ̂)`` (emulator, its full covariance between the rows).  σ is the
    data's noise sd (known or pooled from replicates), else the residual sd of the fit
    (discrepancy included).  A parameter the data do not inform (singular ``JᵀJ``) gets
    the ratio of pseudo-inverse diagonals.

    Examples
    --------
    >>> from kohpymc.emulator import emulate
    >>> from kohpymc.examples import beam
    >>> data = beam.generate_data(seed=1)
    >>> widening = posterior_widening(emulate(beam.physics_model(), data, runs=60), data)
    >>> bool(1.0 <= widening["E"] < 1.25)
    True
    """
    target = EmulatorsAtData.of(emulator, data)
    return _widening_at(target, _best_fit_parameters(target))


def _widening_at(target: EmulatorsAtData, theta: dict[str, float]) -> dict[str, float]:
    """Parameter -> linearised posterior sd at ``theta`` through the emulators over without.

    With the outputs stacked in their noise's units (``J̃``, ``Σ̃``,
    :meth:`~kohpymc.emulator.at_data.EmulatorsAtData.whitened_linearisation`): the square
    root of ``diag (J̃ᵀ (I + Σ̃)⁻¹ J̃)⁻¹`` over ``diag (J̃ᵀ J̃)⁻¹`` (pseudo-inverses).
    """
    J, cov = target.whitened_linearisation(theta)
    plain = np.diag(np.linalg.pinv(J.T @ J))
    through = np.diag(np.linalg.pinv(J.T @ np.linalg.solve(np.eye(len(J)) + cov, J)))
    ratio = np.sqrt(np.maximum(through, 0.0) / np.maximum(plain, np.finfo(float).tiny))
    return {k: float(r) for k, r in zip(target.parameters, ratio, strict=True)}


def check_at_data(
    emulator: Emulator,
    data: CalibrationData,
    *,
    cache: str | Path | None = None,
    level: float = 0.9,
    max_shift: float = 0.25,
    max_widening: float = MAX_WIDENING,
    warn: bool = True,
    workers: int = 1,
    scheduler: Any = None,
) -> EmulatorCheck:
    """Score the emulator where the calibration will use it: at the data, one simulator run.

    Leave-one-out over the design averages over the whole prior box, most of which the
    posterior never visits; an emulator can pass it and still be wrong by many noise sds
    at the calibration rows near the parameters that fit the data (measured: an n-th order
    reaction, 200 runs over k ∈ [1e-3, 1], LOO coverage 0.92 and relative RMSE 0.08, yet at
    the truth an error of rms 0.09 against noise 0.01 and bands 2× too narrow; the
    posterior 3 of its own sds from the direct one).  So: ``θ̂`` = the parameters whose
    emulator prediction fits the data best (the best run's θ, then L-BFGS-B in the design
    box), the simulator run once at ``θ̂`` on the calibration rows (cached like the design
    runs), and the emulator scored there.  Runs the emulator was fitted to at ``θ̂``
    itself (after :func:`~kohpymc.emulator.refinement.refine_at_data`, ``θ̂`` is often
    such a run's θ) are left out of that prediction, else it would only repeat them.
    Problems: the coverage of the ``level`` bands far below ``level`` (tolerance as in
    :func:`check_emulator`), an emulator error
    larger than the simulator's own misfit to the data (the noise, roughly), or an error
    that moves the least-squares θ by more than ``max_shift`` posterior sds.  That move
    is linearised: with ``J`` the emulator mean's Jacobian at ``θ̂`` and ``r`` the
    emulator's error there, the simulator's least-squares θ lies near
    ``θ̂ - (JᵀJ)⁻¹ Jᵀ r``, in units of the sds ``σ sqrt(diag (JᵀJ)⁻¹)`` (σ the noise sd,
    else the simulator's misfit).  An error below the noise can still move θ by
    several sds, as it is correlated over many rows (decay model, 30 runs: error rms
    0.016 against noise 0.05, predicted move 0.29 sd, actual 0.36).
    A last problem: the emulator's own covariance at ``θ̂`` widening a parameter's
    linearised posterior sd by more than ``max_widening`` (as :func:`posterior_widening`,
    at ``θ̂``).  An accurate mean with wide bands passes the other criteria, yet the
    likelihood's ``Σ_η`` widens the posterior (decay model, 8 runs refined by one round
    around a poor first fit: error rms 0.004 against noise 0.05, bands 0.02, none of
    its runs near the posterior; predicted widening 1.24 and 1.33, sampled 1.22 and
    1.26).  Without a known noise sd, also the emulator moving the noise sd's best fit
    by more than :data:`MAX_NOISE_SHIFT` of its sds (:func:`noise_sd_shift`: its ``Σ_η``
    taking up part of the noise, or its error adding to it), linearised at ``θ̂`` and
    judged only while θ itself moves by less than 2 sds (decay model with 8 % noise,
    10 runs: predicted +1.69, against +1.89 from the joint maximum likelihood through
    the emulator's mean and covariance; oral-dose pharmacokinetics with 5 % proportional
    noise, 99 curves: predicted σ 0.082 → 0.065, −1.3 sds, and the sampled σ_obs was
    0.072 against 0.098 through the simulator, −1.3 of its sds).

    A :class:`~kohpymc.emulator.functional.FunctionalEmulator` is checked the same way
    through :class:`~kohpymc.emulator.functional_at_data.CurvesAtData`: the simulator runs
    one whole curve per scalar setting of the data at ``θ̂``.

    Parameters
    ----------
    emulator : Emulator or FunctionalEmulator
    data : CalibrationData
        The calibration data (inputs and outputs).
    cache : path, optional
        Cache folder of the simulator runs (a rerun then runs nothing).
    level : float
        Nominal coverage of the bands.
    max_shift : float
        Largest allowed move of the least-squares θ, in posterior sds.
    max_widening : float
        Largest allowed widening of a parameter's linearised posterior sd at ``θ̂``.
    warn : bool
        Issue an :class:`EmulatorWarning` listing the problems (:func:`warn_at_data`).
    workers, scheduler :
        Where the simulator run goes (:func:`kohpymc.run_tasks`).

    Returns
    -------
    EmulatorCheck
        ``kind = "at the calibration data"``; ``simulated`` the simulator at ``θ̂``.

    Examples
    --------
    >>> from kohpymc.emulator import Emulator, design_box, run_design, space_filling_design
    >>> from kohpymc.examples import beam
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 30))
    >>> check = check_at_data(Emulator(runs, physics), data, warn=False)
    >>> check.kind, check.fit, round(check.shift["E"], 1)  # E's fit moved 1.2 sds
    ('at the calibration data', False, -1.2)
    """
    target = EmulatorsAtData.of(emulator, data)
    check = check_target_at_data(
        target, cache=cache, level=level, max_shift=max_shift, max_widening=max_widening,
        workers=workers, scheduler=scheduler,
    )  # fmt: skip
    if warn:
        warn_at_data(emulator, check)
    return check


@dataclass
class OutputsCheck:
    """The check at the data of several outputs' emulators, at their joint best fit.

    Attributes
    ----------
    checks : dict of str to EmulatorCheck
        Output -> its check at the joint ``θ̂`` (its ``shift``: how far its own error
        moves the joint least-squares θ, in joint posterior sds).
    point : dict
        The joint best fit ``θ̂``.
    shift : dict
        Parameter -> how far all the outputs' errors together move the joint
        least-squares θ, in joint posterior sds (the sum of the outputs' shifts).
    joint_problems : list of str
        The problems of the joint shift and widening.
    widening : dict or None
        Parameter -> linearised posterior sd at ``θ̂`` through the emulators over that
        through the simulator (all outputs; :func:`check_emulators_at_data`).

    Examples
    --------
    >>> empty = np.empty(0)
    >>> one = EmulatorCheck("at the calibration data", empty, empty, empty, problems=["off"])
    >>> OutputsCheck({"u": one}, {"E": 200.0}, {"E": 0.1}).problems
    ['u: off']
    """

    checks: dict[str, EmulatorCheck]
    point: dict[str, float]
    shift: dict[str, float]
    joint_problems: list[str] = field(default_factory=list)
    widening: dict[str, float] | None = None

    @property
    def problems(self) -> list[str]:
        """Every output's problems (named) and the joint ones."""
        named = [f"{k}: {p}" for k, check in self.checks.items() for p in check.problems]
        return named + list(self.joint_problems)

    @property
    def fit(self) -> bool:
        """No problems found."""
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        """The joint point, shift and problems; each output's ``check_at_data`` fields."""
        return {
            "kind": "at the calibration data (joint)",
            "point": dict(self.point),
            "shift": dict(self.shift),
            "widening": self.widening,
            "problems": self.problems,
            "outputs": {k: check.to_dict() for k, check in self.checks.items()},
        }


def check_emulators_at_data(
    target: EmulatorsAtData,
    *,
    cache: str | Path | None = None,
    level: float = 0.9,
    max_shift: float = 0.25,
    max_widening: float = MAX_WIDENING,
    workers: int = 1,
    scheduler: Any = None,
) -> OutputsCheck:
    """:func:`check_at_data` over every output at once, at the outputs' joint best fit.

    ``θ̂`` minimises the outputs' squared errors, each output's weighted by ``1/σ_k²``
    (its noise sd; without one, by the inverse variance of its data); the simulator runs
    once at ``θ̂`` on the distinct calibration rows of all outputs (one call gives them
    all; cached).  Each output is scored as by :func:`check_at_data` (coverage, error
    against its simulator misfit), and the move of the joint least-squares θ is
    linearised over the stacked outputs, each in its noise's units:
    ``-(J̃ᵀJ̃)⁻¹ J̃ₖᵀ r̃ₖ`` per output (``J̃ₖ = Jₖ/σₖ``, ``r̃ₖ = rₖ/σₖ``) in the joint
    sds ``√diag(J̃ᵀJ̃)⁻¹``.  An output whose error moves θ by more than ``max_shift``
    sds fails the check, and so does the sum of the outputs' moves.  No warning
    (:func:`warn_at_data`).

    Parameters
    ----------
    target : EmulatorsAtData
        The simulator, its emulators and their data.
    cache, level, max_shift, max_widening, workers, scheduler :
        As for :func:`check_at_data`.

    Returns
    -------
    OutputsCheck

    Examples
    --------
    >>> from kohpymc.emulator import EmulatorsAtData
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> from kohpymc.multi_output import emulate_outputs
    >>> physics, data = bm.physics_model(), bm.generate_data()
    >>> target = EmulatorsAtData.of_outputs(physics, emulate_outputs(physics, data, runs=20),
    ...                                     data)
    >>> check = check_emulators_at_data(target)
    >>> sorted(check.checks), check.fit
    (['strain', 'u'], False)
    """
    theta = _best_fit_parameters(target)
    simulated = target.simulated_at(theta, cache=cache, workers=workers, scheduler=scheduler)
    checks = {k: _scored(target, k, theta, simulated[k], level) for k in target.data}
    parts = _least_squares_shift(target, checks)
    joint = "joint " if len(checks) > 1 else ""
    for k, check in checks.items():
        check.shift = parts[k]
        check.problems += _moved(
            parts[k], max_shift, f"{_where(target, theta)} its error moves the {joint}"
        )
        check.problems += _noise_moved(target, k, check)
    total = {p: float(sum(part[p] for part in parts.values())) for p in theta}
    widening = _widening_at(target, theta)
    result = OutputsCheck(checks, theta, total, widening=widening)
    if len(checks) > 1:
        together = f"{_where(target, theta)} the outputs' errors together move the joint "
        result.joint_problems = _moved(total, max_shift, together)
    widened = _widened(widening, max_widening, _where(target, theta))
    if target.single:
        checks[SINGLE].widening = widening
        checks[SINGLE].problems += widened
    else:
        result.joint_problems += widened
    return result


def _widened(widening: dict[str, float], max_widening: float, where: str) -> list[str]:
    """The problem of a linearised posterior sd widened beyond ``max_widening`` (or none)."""
    wide = {k: v for k, v in widening.items() if v > max_widening}
    if not wide:
        return []
    named = ", ".join(f"{k} {v:.3g}×" for k, v in wide.items())
    return [
        f"{where} its own uncertainty widens the posterior sd beyond the simulator's "
        f"({named}; > {max_widening}×, linearised): the runs there are too few"
    ]


def check_target_at_data(target: EmulatorsAtData, **options: Any) -> Any:
    """:func:`check_emulators_at_data`; for a single-output simulator its one check.

    Returns
    -------
    EmulatorCheck (one output) or OutputsCheck
    """
    joint = check_emulators_at_data(target, **options)
    return joint.checks[SINGLE] if target.single else joint


def warn_at_data(
    emulator: Emulator | EmulatorsAtData | None,
    check: EmulatorCheck | OutputsCheck,
    advice: str = "add runs ([emulator] runs, refine_at_data, or sequential rounds)",
    *,
    design_problems: Sequence[str] = (),
) -> None:
    """The :class:`EmulatorWarning` of a failed :func:`check_at_data` (none if it passed).

    ``emulator`` is the emulator, or for several outputs their :class:`EmulatorsAtData`.
    ``design_problems`` (from :func:`check_emulator` over the design) are named too.

    Examples
    --------
    >>> import numpy as np
    >>> check = EmulatorCheck("at the calibration data", np.ones(2), np.ones(2), np.ones(2))
    >>> warn_at_data(None, check)  # no problems: no warning
    """
    if check.fit or emulator is None:
        return
    if isinstance(emulator, EmulatorsAtData) and emulator.single:
        emulator = emulator.first
    if isinstance(emulator, EmulatorsAtData):
        what = f"emulators of {emulator.simulator.name!r} ({emulator.n_runs} runs) are"
    else:
        runs = getattr(emulator, "runs_noun", "runs")
        what = f"emulator of {emulator.physics.name!r} ({emulator.n_runs} {runs}) is"
    named = [_without_advice(problem) for problem in design_problems]
    design = f"; over its design, {'; '.join(named)}" if named else ""
    warn_user(
        f"{what} not fit for this calibration: {'; '.join(check.problems)}{design}; {advice}",
        EmulatorWarning,
    )


def _without_advice(problem: str) -> str:
    """A design problem without its own advice (the warning ends with one).

    Examples
    --------
    >>> _without_advice("leave-one-out RMSE is 0.6 (> 0.1): add runs (see kohpymc.emulator)")
    'leave-one-out RMSE is 0.6 (> 0.1)'
    """
    return problem.split(": add runs (")[0]


def _scored(
    target: EmulatorsAtData, name: str, theta: dict[str, float], simulated: np.ndarray, level: float
) -> EmulatorCheck:
    """One output's emulator scored against the simulator at ``theta``: coverage, error."""
    data = target.data[name]
    mean, var = target.predicted_at(name, theta)
    misfit = float(np.sqrt(np.mean((np.asarray(data.y, float) - simulated) ** 2)))
    check = EmulatorCheck(
        "at the calibration data", simulated, mean, np.sqrt(var), level, point=theta, misfit=misfit
    )
    low, _ = coverage_bounds(level, simulated.size)
    where = _where(target, theta)
    if check.coverage < low:
        check.problems.append(
            f"{where} its {level:.0%} bands cover {check.coverage:.2f} of the simulator's "
            f"outputs at the calibration rows (< {low:.2f})"
        )
    if check.rmse > misfit:
        check.problems.append(
            f"{where} its error at the calibration rows (rms {check.rmse:.3g}) exceeds the "
            f"simulator's own misfit to the data (rms {misfit:.3g})"
        )
    return check


def _where(target: EmulatorsAtData, theta: dict[str, float]) -> str:
    fit = "the emulator's best fit" if len(target.data) == 1 else "the emulators' joint best fit"
    return f"at {_format_theta(theta)} ({fit} to the data)"


def _moved(shift: dict[str, float], max_shift: float, what: str) -> list[str]:
    """The problem of a move of the least-squares θ beyond ``max_shift`` sds (or none)."""
    moved = {k: v for k, v in shift.items() if abs(v) > max_shift}
    if not moved:
        return []
    named = ", ".join(f"{k} {v:+.2g}" for k, v in moved.items())
    return [f"{what}least-squares θ by about {named} posterior sds (linearised; > {max_shift})"]


def noise_sd_shift(
    simulator_residual: np.ndarray, emulator_residual: np.ndarray, covariance: np.ndarray
) -> tuple[float, float, float]:
    """How far an emulator moves the best fit of an unknown noise sd, in its posterior sds.

    Through the simulator the noise sd's maximum-likelihood value at θ is the rms of its
    residual ``r_s``; through the emulator it maximises ``log N(r_e; 0, Σ_η + σ² I)``
    (``r_e`` the emulator mean's residual, ``Σ_η`` its covariance on the rows).  An
    emulator whose own variance is a fair part of the noise takes that part up, and an
    unknown σ is then estimated low.  The move is given in σ's large-sample sd,
    ``σ̂ / √(2n)``.

    Parameters
    ----------
    simulator_residual, emulator_residual : numpy.ndarray
        ``y - simulator(θ)`` and ``y - emulator mean(θ)`` on the calibration rows.
    covariance : numpy.ndarray
        ``Σ_η`` on those rows.

    Returns
    -------
    (float, float, float)
        σ̂ through the simulator, σ̂ through the emulator, the move in σ's sds.

    Examples
    --------
    >>> import numpy as np
    >>> r = np.random.default_rng(0).normal(0.0, 1.0, 200)
    >>> sim, emu, move = noise_sd_shift(r, r, 0.5 * np.eye(200))  # Σ_η half the variance
    >>> round(emu / sim, 2), bool(move < -4)
    (0.68, True)
    """
    from scipy.optimize import minimize_scalar

    n = simulator_residual.size
    simulated = float(np.sqrt(np.mean(simulator_residual**2)))
    if simulated <= 0.0:
        return 0.0, 0.0, 0.0
    eigenvalues, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    eigenvalues = np.maximum(eigenvalues, 0.0)
    z2 = (vectors.T @ emulator_residual) ** 2

    def minus_log_likelihood(log_sd: float) -> float:
        total = eigenvalues + np.exp(2.0 * log_sd)
        return 0.5 * float(np.sum(np.log(total) + z2 / total))

    centre = np.log(simulated)
    best = minimize_scalar(
        minus_log_likelihood, bounds=(centre - 12.0, centre + 3.0), method="bounded",
        options={"xatol": 1e-6},
    )  # fmt: skip
    emulated = float(np.exp(best.x))
    return simulated, emulated, (emulated - simulated) / (simulated / np.sqrt(2.0 * n))


def _noise_moved(target: EmulatorsAtData, name: str, check: EmulatorCheck) -> list[str]:
    """The problem of an emulator moving an unknown noise sd's best fit (or none).

    Linearised at ``θ̂``: not judged when the emulator moves θ itself by more than
    :data:`_LINEAR_SHIFT` sds (that is a problem already, and the linearisation is off).
    """
    data = target.data[name]
    moved = max((abs(v) for v in (check.shift or {}).values()), default=0.0)
    if data.noise_sd is not None or moved > _LINEAR_SHIFT:
        return []
    y = np.asarray(data.y, float)
    J, _, covariance = target.linearised(name, check.point)
    # the simulator's residual at its own least-squares θ (linearised), not at θ̂
    residual = y - check.simulated
    step, *_ = np.linalg.lstsq(J, residual, rcond=None)
    simulated, emulated, move = noise_sd_shift(residual - J @ step, y - check.mean, covariance)
    check.noise_shift = move
    if abs(move) <= MAX_NOISE_SHIFT:
        return []
    return [
        f"{_where(target, check.point)} its variance and error move the unknown noise sd's "
        f"best fit from {simulated:.3g} (the simulator's) to {emulated:.3g}, {move:+.2g} of its "
        f"posterior sds (> {MAX_NOISE_SHIFT}): σ would be estimated {'low' if move < 0 else 'high'}"
    ]


def _least_squares_shift(
    target: EmulatorsAtData, checks: dict[str, EmulatorCheck]
) -> dict[str, dict[str, float]]:
    """Output -> how far its error moves the joint least-squares θ, in posterior sds.

    Linearised over the stacked outputs in their noise's units (σ the noise sd, else the
    simulator's misfit): the simulator's joint least-squares θ lies near
    ``θ̂ - Σₖ (J̃ᵀJ̃)⁻¹ J̃ₖᵀ r̃ₖ``; for one output ``θ̂ - (JᵀJ)⁻¹Jᵀr`` in sds
    ``σ √diag (JᵀJ)⁻¹``.  A zero noise (a simulator fitting the data exactly) gives 0.
    """
    names = target.parameters
    blocks, errors = {}, {}
    for k, check in checks.items():
        data = target.data[k]
        J, _, _ = target.linearised(k, check.point)
        noise = float((data.noise_sd if data.noise_sd is not None else check.misfit) or 0.0)
        if noise <= 0.0:
            return {k: dict.fromkeys(names, 0.0) for k in checks}
        blocks[k], errors[k] = J / noise, (check.simulated - check.mean) / noise
    stacked = np.vstack(list(blocks.values()))
    inverse = np.linalg.pinv(stacked.T @ stacked)
    sds = np.sqrt(np.maximum(np.diag(inverse), 0.0))
    parts = {}
    for k, J in blocks.items():
        move = -inverse @ J.T @ errors[k]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(sds > 0, move / sds, 0.0)
        parts[k] = {p: float(v) for p, v in zip(names, ratio, strict=True)}
    return parts


def _best_fit_parameters(target: EmulatorsAtData, starts: int = 5) -> dict[str, float]:
    """θ minimising the emulators' squared errors at the data, in the design box.

    Searched in the emulators' unit coordinates (the log for a parameter spanning decades:
    in natural units an A over 1e-2..1e8 and a Q over 1e5..4e5 gave L-BFGS-B steps of the
    wrong size by ten orders), from the ``starts`` design points that fit best.  Each
    output's squared error is weighted by ``1/σ_k²`` (its noise sd; without one, by the
    inverse variance of its data), and the sum is divided by the data's own weighted
    spread (for one output: the squared error relative to the data's spread).
    """
    from scipy.optimize import minimize

    first, names = target.first, target.parameters
    ys = {k: np.asarray(d.y, float) for k, d in target.data.items()}
    weights = {k: _output_weight(d, ys[k]) for k, d in target.data.items()}
    # in units of the data's own spread: an SSE of 1e-12 (rates of 1e-5) has gradients
    # below L-BFGS-B's absolute tolerance, and it stopped where it started
    spread = sum(weights[k] * float(np.sum((y - y.mean()) ** 2)) for k, y in ys.items()) or 1.0

    def sse(unit: np.ndarray) -> float:
        values = dict(zip(names, first.parameters_from_unit(np.clip(unit, 0, 1)), strict=True))
        total = 0.0
        for k, y in ys.items():
            mean, _ = target.emulators[k].predict(target.data[k].inputs, values)
            total += weights[k] * float(np.sum((y - mean) ** 2))
        return total / spread

    units = np.clip(first.parameters_to_unit(target.run_thetas()), 0.0, 1.0)
    ranked = sorted(units, key=sse)[:starts]
    fits = [minimize(sse, u, method="L-BFGS-B", bounds=[(0.0, 1.0)] * len(names)) for u in ranked]
    best = min(fits, key=lambda fit: fit.fun)
    unit = best.x if best.fun <= sse(ranked[0]) else ranked[0]
    return {k: float(v) for k, v in zip(names, first.parameters_from_unit(unit), strict=True)}


def _output_weight(data: CalibrationData, y: np.ndarray) -> float:
    """``1/σ²`` of an output's data (its noise sd, else the variance of its values)."""
    if data.noise_sd is not None:
        return 1.0 / float(data.noise_sd) ** 2
    variance = float(np.var(y))
    return 1.0 / variance if variance > 0 else 1.0


def _format_theta(theta: dict[str, float]) -> str:
    return "{" + ", ".join(f"{k}={v:.4g}" for k, v in theta.items()) + "}"
