r"""Posteriors that lie against a bound of their prior, found at the mode and in the draws.

When the physics model misses a mechanism, its parameters may run to the edge of their
prior box to make up for it: on the dielectric stand-in without its polarisation current
(M0), Φ_B piles against its upper bound 1.4 and ln γ against its lower bound 16.1.  The
posterior is then the prior box's, not the data's, and NUTS pays for the wall (long
trajectories, divergences).  :func:`against_bounds` is the one check, on the bounded
(``Uniform``-like, interval-transformed) parameters:

* **at the mode**, before sampling (:func:`hits_at_mode`, from
  :class:`kohpymc.presampling.PreSampling`): the mode lies within :data:`MODE_SDS`
  Laplace standard deviations of a finite bound (measured on the log scale for a
  positive parameter whose box spans :data:`LOG_SCALE_RATIO` or more), and
  ± :data:`MODE_SDS` sds fit in the box (a posterior as wide as the box reaches both
  bounds: the prior's spread, not a pile-up).  The mode is PyMC's, in the
  interval-transformed value space, whose Jacobian keeps it off the bound: a posterior
  truncated by the bound has its mode there 1 (exponentially rising density) to 1.4
  (half-normal) Laplace sds from it, one well inside has it many sds away;
* **in the draws**, after sampling (:func:`hits_in_draws`, from
  :func:`kohpymc.sampling.sample_posterior`): at least :data:`DRAW_SHARE` of the draws
  lie within :data:`NEAR_FRACTION` of the prior width of a bound (1 % of them would be
  there under a flat posterior over the whole box), and their outermost percentile on that
  side is within :data:`EDGE_FRACTION` of their own 1–99 % range from it, but not on both
  sides (draws that reach both bounds are the prior's spread, as at the mode) (so a posterior
  near a bound in the box's units but clear of it on its own scale — τ ≈ 10⁻³ under
  ``LogUniform(1e-6, 1)`` — is not reported).  For a positive parameter whose box spans
  :data:`LOG_SCALE_RATIO` or more, the posterior's own scale is the log: a posterior spread
  over decades (10⁻⁵–10⁻² under ``LogUniform(1e-6, 1)``) reaches 1e-6 on the box's scale
  (0.1 % of its range) but stays a decade clear of it on its own.

Each finding is a :class:`BoundHit`, stored in the result's provenance (``prior_bounds``
in ``idata.attrs["presampling"]`` and ``idata.attrs["sampling"]``) and issued as a
:class:`PriorBoundWarning` naming the parameter, the bound and the value.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from scipy.special import expit

from kohpymc.value_space import ValueSpace
from kohpymc.warning_filters import warn_user

__all__ = [
    "DRAW_SHARE",
    "EDGE_FRACTION",
    "LOG_SCALE_RATIO",
    "MODE_SDS",
    "NEAR_FRACTION",
    "BoundHit",
    "PriorBoundWarning",
    "against_bounds",
    "hits_at_mode",
    "interval_elements",
    "interval_labels",
    "hits_in_draws",
    "warn_hits",
]

#: the mode lies against a bound when closer to it than this many Laplace sds (a truncated
#: posterior has its mode 1-1.4 sds off the bound in interval coordinates; the beam's M4,
#: whose E is only thinned by the bound 300, had it at 2.0)
MODE_SDS = 1.5
#: draws closer to a bound than this fraction of the prior width are "at" the bound
NEAR_FRACTION = 0.01
#: the posterior lies against a bound when at least this share of draws is at it
DRAW_SHARE = 0.1
#: ... and its outermost percentile is this close to the bound, in units of its 1-99 % range
EDGE_FRACTION = 0.05
#: positive parameters whose box spans at least this ratio reach a bound (EDGE_FRACTION) on the
#: log scale
LOG_SCALE_RATIO = 10.0


class PriorBoundWarning(UserWarning):
    """The posterior of a bounded parameter lies against a bound of its prior."""


@dataclass(frozen=True)
class BoundHit:
    """A parameter whose posterior lies against a prior bound.

    Attributes
    ----------
    parameter : str
        ``"phi_B"``, or ``"theta[2]"`` for an element of a vector parameter.
    side : str
        ``"lower"`` or ``"upper"``.
    bound : float
    value : float
        The mode (``evidence="mode"``) or the median of the draws (``"draws"``).
    evidence : str
        ``"mode"`` or ``"draws"``.
    measure : float
        Laplace sds from the mode to the bound, or the share of draws at the bound.
    index : int
        Flat index in PyMC's value space (from :func:`hits_at_mode`,
        :func:`hits_in_draws`), else the position in ``names``.

    Examples
    --------
    >>> BoundHit("phi_B", "upper", 1.4, 1.3995, "mode", 0.8).message()[:52]
    'phi_B: the posterior lies against its upper prior bo'
    """

    parameter: str
    side: str
    bound: float
    value: float
    evidence: str
    measure: float
    index: int = -1

    def message(self) -> str:
        """One line naming the parameter, the bound and the value, and what to do."""
        found = (
            f"mode {self.value:.6g}, {self.measure:.2g} Laplace sd from it"
            if self.evidence == "mode"
            else f"{self.measure:.0%} of draws within {NEAR_FRACTION:.0%} of the prior "
            f"width of it, median {self.value:.6g}"
        )
        return (
            f"{self.parameter}: the posterior lies against its {self.side} prior bound "
            f"{self.bound:.6g} ({found}): the prior box, not the data, limits it — widen "
            "the prior or add a discrepancy"
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain values for provenance, with the message."""
        return {**asdict(self), "message": self.message()}


def against_bounds(
    names: Sequence[str],
    lower: np.ndarray,
    upper: np.ndarray,
    *,
    mode: np.ndarray | None = None,
    sd: np.ndarray | None = None,
    draws: np.ndarray | None = None,
    evidence: str = "mode",
    sds: float = MODE_SDS,
) -> list[BoundHit]:
    """Parameters whose posterior lies against a finite bound (see the module docstring).

    Parameters
    ----------
    names : sequence of str
        One per bounded parameter (element).
    lower, upper : ndarray
        Their prior bounds (``±inf`` or NaN: no bound on that side).
    mode, sd : ndarray, optional
        The mode and its Laplace sd in the parameters' units (``evidence="mode"``).
    draws : ndarray, optional
        Posterior draws, shape ``(n, len(names))`` (``evidence="draws"``).
    evidence : {"mode", "draws"}
    sds : float
        At the mode: how many Laplace sds from a bound count as against it (default
        :data:`MODE_SDS`).

    Returns
    -------
    list of BoundHit

    Examples
    --------
    >>> hits = against_bounds(["a", "b"], np.array([0.0, 0.0]), np.array([1.0, 1.0]),
    ...                       mode=np.array([0.999, 0.5]), sd=np.array([0.001, 0.1]))
    >>> [(h.parameter, h.side) for h in hits]
    [('a', 'upper')]
    """
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if evidence == "mode":
        value = np.asarray(mode, float)
        # on the posterior's own scale: the log for a positive box spanning decades, where
        # a mode at 6e-5 under LogUniform(1e-9, 1e-3) with a linearised sd of 1e-4 is 0.5
        # "sds" from 1e-9 but eleven e-folds clear of it (near a bound both scales agree)
        own, own_sd, own_lower, own_upper = _mode_on_own_scale(value, sd, lower, upper)
        measures = [
            (np.asarray(own - own_lower) / own_sd, lower),
            (np.asarray(own_upper - own) / own_sd, upper),
        ]
        # a posterior as wide as the box (±MODE_SDS sds do not fit in it) is the prior's
        # spread, not a pile-up at one side: it reaches both bounds
        narrow = 2.0 * sds * own_sd < own_upper - own_lower
        near = [(m < sds) & narrow for m, _ in measures]
    else:
        x = np.asarray(draws, float).reshape(-1, len(names))
        value = np.median(x, axis=0)
        width = NEAR_FRACTION * (upper - lower)
        with np.errstate(invalid="ignore"):  # a one-sided interval: no width, no hit
            measures = [(np.mean(x < lower + width, axis=0), lower)]
            measures.append((np.mean(x > upper - width, axis=0), upper))
        # and the draws reach the bound on the posterior's own scale: its outermost
        # percentile within EDGE_FRACTION of its 1-99 % range from the bound (a posterior
        # near a bound in the box's units but well clear of it on its own scale, as
        # tau ~ 1e-3 under LogUniform(1e-6, 1), is not truncated by it); for a positive
        # parameter whose box spans decades that scale is the log
        own, own_lower, own_upper = _log_where_wide(x, lower, upper)
        q01, q99 = np.quantile(own, [0.01, 0.99], axis=0)
        spread = np.maximum(q99 - q01, np.finfo(float).tiny)
        reach = [
            (q01 - own_lower) / spread < EDGE_FRACTION,
            (own_upper - q99) / spread < EDGE_FRACTION,
        ]
        # draws that reach both bounds are the prior's spread (the data do not inform the
        # parameter), not a pile-up at one side: as at the mode
        one_side = ~(reach[0] & reach[1])
        near = [(m >= DRAW_SHARE) & r & one_side for (m, _), r in zip(measures, reach, strict=True)]
    hits = []
    for (measure, bound), close, side in zip(measures, near, ("lower", "upper"), strict=True):
        for i in np.flatnonzero(close & np.isfinite(bound) & np.isfinite(measure)):
            hit = BoundHit(
                names[int(i)], side, float(bound[i]), float(value[i]), evidence, 0.0, int(i)
            )
            hits.append(replace(hit, measure=float(measure[i])))
    return hits


def _wide_positive(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Positive boxes spanning ``LOG_SCALE_RATIO`` or more: judged on the log scale."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return (lower > 0) & np.isfinite(upper) & (upper >= LOG_SCALE_RATIO * lower)


def _mode_on_own_scale(
    value: np.ndarray, sd: Any, lower: np.ndarray, upper: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mode, sd and bounds, on the log scale (sd by the delta method) where the box is wide."""
    sd = np.broadcast_to(np.asarray(sd, float), value.shape)
    wide = _wide_positive(lower, upper)
    if not wide.any():
        return value, sd, lower, upper
    value, sd, lower, upper = value.copy(), sd.copy(), lower.copy(), upper.copy()
    sd[wide] = sd[wide] / value[wide]
    value[wide] = np.log(value[wide])
    lower[wide], upper[wide] = np.log(lower[wide]), np.log(upper[wide])
    return value, sd, lower, upper


def _log_where_wide(
    x: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draws and bounds, on the log scale for positive boxes spanning ``LOG_SCALE_RATIO``+."""
    wide = _wide_positive(lower, upper)
    if not wide.any():
        return x, lower, upper
    x, lower, upper = x.copy(), lower.copy(), upper.copy()
    x[:, wide] = np.log(np.maximum(x[:, wide], lower[wide]))
    lower[wide], upper[wide] = np.log(lower[wide]), np.log(upper[wide])
    return x, lower, upper


def interval_elements(
    space: ValueSpace,
) -> tuple[list[str], np.ndarray, list[tuple[str, int, int]]]:
    """Labels and flat indices of the interval elements, and ``(rv name, start, size)``.

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     s = pm.HalfNormal("s", 1.0)
    ...     a = pm.Uniform("a", 0.0, 1.0, shape=2)
    >>> labels, index, _ = interval_elements(value_space(model))
    >>> labels, index.tolist()
    (['a[0]', 'a[1]'], [1, 2])
    >>> interval_labels(value_space(model))
    {1: 'a[0]', 2: 'a[1]'}
    """
    labels, index, blocks = [], [], []
    start = 0
    for rv, shape in zip(space.model.free_RVs, space.shapes, strict=True):
        size = int(np.prod(shape, dtype=int))
        blocks.append((rv.name, start, size))
        for k in range(size):
            if space.transforms[start + k] == "interval":
                labels.append(rv.name if shape == () else f"{rv.name}[{k}]")
                index.append(start + k)
        start += size
    return labels, np.asarray(index, dtype=int), blocks


def interval_labels(space: ValueSpace) -> dict[int, str]:
    """The label of each interval element (:func:`interval_elements`) by its flat index.

    Examples
    --------
    See :func:`interval_elements`.
    """
    labels, index, _ = interval_elements(space)
    return dict(zip(index.tolist(), labels, strict=True))


def hits_at_mode(
    space: ValueSpace, mode: np.ndarray, value_sd: np.ndarray, *, sds: float = MODE_SDS
) -> list[BoundHit]:
    """:func:`against_bounds` at the value-space ``mode`` with its Laplace sd ``value_sd``.

    Both are mapped to the parameters' units by the interval transform
    ``x = a + (b − a)·expit(v)`` (the sd by its derivative).

    Examples
    --------
    >>> import pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     a = pm.Uniform("a", 0.0, 1.0)
    >>> space = value_space(model)
    >>> [h.side for h in hits_at_mode(space, np.array([8.0]), np.array([1.0]))]
    ['upper']
    """
    labels, index, _ = interval_elements(space)
    if not labels:
        return []
    a, b = space.lower[index], space.upper[index]
    s = expit(np.asarray(mode, float)[index])
    x = a + (b - a) * s
    sd = np.asarray(value_sd, float)[index] * (b - a) * s * (1.0 - s)
    hits = against_bounds(labels, a, b, mode=x, sd=sd, evidence="mode", sds=sds)
    return [replace(hit, index=int(index[hit.index])) for hit in hits]


def hits_in_draws(space: ValueSpace, posterior: Any) -> list[BoundHit]:
    """:func:`against_bounds` on the draws of ``posterior`` (an ``idata.posterior``).

    Examples
    --------
    >>> import arviz as az, pymc as pm
    >>> from kohpymc.value_space import value_space
    >>> with pm.Model() as model:
    ...     a = pm.Uniform("a", 0.0, 1.0)
    >>> post = az.from_dict(posterior={"a": np.linspace(0.99, 1.0, 50)[None]}).posterior
    >>> [h.side for h in hits_in_draws(value_space(model), post)]
    ['upper']
    """
    labels, index, blocks = interval_elements(space)
    if not labels:
        return []
    columns = [
        np.asarray(posterior[name].values, float).reshape(-1, size)
        for name, _, size in blocks
        if size
    ]
    draws = np.concatenate(columns, axis=1)[:, index]
    hits = against_bounds(
        labels, space.lower[index], space.upper[index], draws=draws, evidence="draws"
    )
    return [replace(hit, index=int(index[hit.index])) for hit in hits]


def warn_hits(hits: Sequence[BoundHit], where: str = "") -> None:
    """One :class:`PriorBoundWarning` per hit; ``where`` (e.g. "at the mode") ends it.

    Examples
    --------
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as seen:
    ...     warnings.simplefilter("always")
    ...     warn_hits([BoundHit("a", "upper", 1.0, 0.999, "mode", 1.0)], "at the mode")
    >>> str(seen[0].message)[-19:]
    '(found at the mode)'
    """
    suffix = f" (found {where})" if where else ""
    for hit in hits:
        warn_user(hit.message() + suffix, PriorBoundWarning)
