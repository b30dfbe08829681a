"""Closed-form evidence of candidate terms on a linearised residual (see :mod:`kohpymc.discovery`).

Around the calibrated point θ̂ the residual ``r = y - G(x; θ̂)`` is modelled as

    r = J Δθ + [1, Φ_S] c + ε,      ε ~ N(0, σ² I),

with ``J = ∂G/∂θ`` at θ̂ (one Gauss-Newton step: Δθ re-fits the physics parameters jointly
with the terms), the constant ``1`` (unless the physics parameters can already shift the
level) and the columns ``Φ_S`` of a candidate subset S.  Priors (Zellner's g-prior with
the physics parameters as common parameters, Liang et al. 2008, JASA 103:410):

* ``Δθ`` flat (common to every model, so its improper constant cancels in a ratio);
* ``c | σ ~ N(0, g σ² (Φ̃ᵀΦ̃)⁻¹)`` with ``Φ̃`` the added columns with the span of ``J``
  projected out, ``g = n`` (unit information) by default;
* ``σ`` known (the data's noise sd) or ``p(σ) ∝ 1/σ`` (integrated out, never plugged in).

With ``p = rank J``, ``k`` added columns, ``RSS₀`` the residual sum of squares of the
physics-only fit and ``RSS_S`` that with the terms, the Bayes factor against "nothing
missing" is, σ known::

    log B = -k/2 log(1 + g) + g/(1 + g) · (RSS₀ - RSS_S) / (2σ²)

and σ integrated out::

    log B = (n - p - k)/2 log(1 + g) - (n - p)/2 log(1 + g RSS_S/RSS₀)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["TermSelection", "log_bayes_factor"]


def log_bayes_factor(
    rss0: float,
    rss: np.ndarray | float,
    n: int,
    p: int,
    k: np.ndarray | int,
    *,
    noise_sd: float | None,
    g: float | None = None,
) -> np.ndarray:
    """Log Bayes factor of ``k`` added columns against the physics-only fit.

    Parameters
    ----------
    rss0 : float
        Residual sum of squares after the Gauss-Newton re-fit of θ alone.
    rss : array or float
        Residual sum of squares with the added columns (one per subset).
    n, p : int
        Number of rows and rank of the physics Jacobian.
    k : array or int
        Number of added columns per subset (a fitted scale counts as one more).
    noise_sd : float or None
        Known noise sd, or None (σ integrated out with ``p(σ) ∝ 1/σ``).
    g : float, optional
        The g of the g-prior; default ``n``.

    Returns
    -------
    array
        ``log B`` per subset.

    Examples
    --------
    >>> round(float(log_bayes_factor(10.0, 10.0, 20, 1, 1, noise_sd=None)), 3)  # no fit gain
    -1.522
    >>> float(log_bayes_factor(10.0, 2.0, 20, 1, 1, noise_sd=1.0)) > 0
    True
    """
    g = float(n if g is None else g)
    rss = np.asarray(rss, dtype=float)
    k = np.asarray(k, dtype=float)
    if noise_sd is not None:
        return -0.5 * k * np.log1p(g) + g / (1 + g) * (rss0 - rss) / (2 * noise_sd**2)
    ratio = np.clip(rss / rss0, 0.0, 1.0) if rss0 > 0 else np.ones_like(rss)
    return 0.5 * (n - p - k) * np.log1p(g) - 0.5 * (n - p) * np.log1p(g * ratio)


@dataclass
class TermSelection:
    """Result of :func:`kohpymc.discovery.select_terms`: a posterior over explanations.

    Attributes
    ----------
    best : tuple of str
        Names of the most probable explanation (empty: nothing missing; ``("1",)``: a
        constant offset).
    probability_none : float
        Posterior probability that nothing is missing.
    inclusion : dict name -> float
        Posterior inclusion probability of each term that appears in an explanation.
    subsets : list of (tuple of str, float)
        Explanations with their posterior probabilities, most probable first ("nothing
        missing" is the empty tuple).
    rejected : dict name -> str
        Candidates dropped before the comparison, with the reason.
    merged : dict name -> str
        Candidates equal to another on the data (up to the physics parameters and a
        constant): name -> the name kept.
    p_value : float or None
        Share of simulated null residuals with a probability of "nothing missing" at
        most the observed one (None when not calibrated).
    false_alarm : float
        The false-alarm rate the decision is calibrated to.
    terms : dict name -> CandidateTerm
        Terms of the explanations (shaped ones at their fitted scale).
    log_bayes_factors : dict tuple -> float
        Log Bayes factor of each explanation against "nothing missing".
    constant : bool
        Whether a constant offset is part of every explanation (False when the physics
        parameters can shift the level themselves).
    """

    best: tuple[str, ...]
    probability_none: float
    inclusion: dict[str, float]
    subsets: list[tuple[tuple[str, ...], float]]
    rejected: dict[str, str] = field(default_factory=dict)
    merged: dict[str, str] = field(default_factory=dict)
    p_value: float | None = None
    false_alarm: float = 0.01
    terms: dict = field(default_factory=dict)
    log_bayes_factors: dict = field(default_factory=dict)
    constant: bool = True

    def plainest(self, factor: float = 3.0) -> tuple[str, ...]:
        """The explanation to name: the most probable one, unless a plainer one is as good.

        Among the non-empty explanations whose probability is within ``factor`` of the most
        probable one (a Bayes factor below 3 is "not worth more than a bare mention", Kass
        and Raftery 1995) and that have as many terms, the one on the fewest inputs; ties go
        to the more probable.  When an input varies little in the data, ``1/t`` and
        ``sqrt(T)/t`` fit alike, and the variants on ``T`` share the probability among
        themselves; naming ``T`` would claim an effect the data do not show.  Terms whose
        inputs are unknown (plain columns) count no inputs.

        Examples
        --------
        >>> from kohpymc.candidates import CandidateTerm
        >>> terms = {"T/t": CandidateTerm("T/t", ("T", "t"), lambda d: d["T"] / d["t"]),
        ...          "1/t": CandidateTerm("1/t", ("t",), lambda d: 1 / d["t"])}
        >>> sel = TermSelection(("T/t",), 0.0, {}, [(("T/t",), 0.5), (("1/t",), 0.45)],
        ...                     terms=terms)
        >>> sel.plainest()
        ('1/t',)
        """
        named = [(subset, p) for subset, p in self.subsets if subset]
        if not named:
            return ()
        top, p_top = named[0]
        size = len([n for n in top if n != "1"])
        near = [
            (len(self.inputs_of(subset)), -p, subset)
            for subset, p in named
            if p * factor >= p_top and len([n for n in subset if n != "1"]) == size
        ]
        return min(near)[2]

    def inputs_of(self, subset: tuple[str, ...]) -> set[str]:
        """The inputs the terms of ``subset`` depend on (unknown for plain columns)."""
        return {i for n in subset if n != "1" for i in getattr(self.terms.get(n), "inputs", ())}

    @property
    def significant(self) -> bool:
        """Whether something is missing at the calibrated false-alarm rate.

        Examples
        --------
        >>> TermSelection((), 0.9, {}, [((), 0.9)], p_value=0.4).significant
        False
        """
        if self.p_value is None:
            return bool(self.probability_none < self.false_alarm)
        return bool(self.p_value <= self.false_alarm)
