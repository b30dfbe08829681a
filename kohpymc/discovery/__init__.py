"""Discovery: which candidate term explains the disagreement between model and data.

This package holds the selection step of the discovery workflow (issue 5, in progress):
Bayesian model comparison of small sets of candidate terms (:mod:`kohpymc.candidates`)
on the residuals of a calibrated model, *linearised in the physics parameters*, so a
term that the physics parameters can mimic earns no credit.

Around the calibrated point θ̂ the residual ``r = y - G(x; θ̂)`` is modelled as::

    r = J Δθ + Φ_S c + ε,   Δθ ~ N(0, diag(s_θ²)),  c ~ N(0, s_c² I),  ε ~ N(0, σ² I)

with ``J = ∂G/∂θ`` at θ̂ and ``Φ_S`` the (unit-sd) columns of a candidate subset S.  The
evidence ``p(r | S)`` is a zero-mean normal with covariance
``σ² I + J diag(s_θ²) Jᵀ + s_c² Φ_S Φ_Sᵀ``, exact for this linear model.  Subsets up to
``max_terms`` are enumerated; the prior gives half its mass to "nothing missing" and
splits the other half equally over the subset sizes and then over the subsets of each
size, which pays for the number of candidates tried (multiplicity control).  A candidate
whose column lies in the span of ``J`` (rank check as in
:func:`kohpymc.identifiability.analyse_matrix`) is rejected with the reason before the
comparison.  With σ unknown it is set per subset to the value that maximises the
evidence (type-II maximum likelihood).
"""

from __future__ import annotations

from kohpymc.discovery.augment import augmented_physics
from kohpymc.discovery.evidence import TermSelection, log_bayes_factor
from kohpymc.discovery.regions import disagreement_regions
from kohpymc.discovery.report import DiscoveryReport
from kohpymc.discovery.selection import null_probabilities, select_terms
from kohpymc.discovery.workflow import discover

__all__ = [
    "TermSelection",
    "select_terms",
    "log_bayes_factor",
    "null_probabilities",
    "DiscoveryReport",
    "augmented_physics",
    "disagreement_regions",
    "discover",
]
