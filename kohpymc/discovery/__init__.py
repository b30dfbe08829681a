"""Discovery: which candidate term explains the disagreement between model and data.

One module per step of :func:`discover`:

* :mod:`~kohpymc.discovery.search` and :mod:`~kohpymc.discovery.evidence`: closed-form
  evidence of small sets of candidate terms (:mod:`kohpymc.candidates`) on the residual
  of the calibrated model, *linearised in the physics parameters* (so a term they can
  mimic earns nothing), σ known or integrated out; :mod:`~kohpymc.discovery.selection`:
  the posterior over explanations and the false-alarm rate calibrated by simulation;
* :mod:`~kohpymc.discovery.drift`: "a parameter varies with an input" and "the output
  scales with an input" terms from the model's own sensitivities;
  :mod:`~kohpymc.discovery.dimensions`: with units, dimensionless (π) groups as
  candidates and the unit of each coefficient;
* :mod:`~kohpymc.discovery.fallback`: which inputs matter (ARD, type-II ML), the K-fold
  check of the closed form inside the calibration data, and the decision to fall back to
  a GP discrepancy ("depends on t; no closed form found");
* :mod:`~kohpymc.discovery.augment`, :mod:`~kohpymc.discovery.regions`,
  :mod:`~kohpymc.discovery.report` and :mod:`~kohpymc.discovery.workflow`: the augmented
  model, the failing ranges, the report and :func:`discover` itself.

The calibration data choose everything (terms, scales, the GP's inputs, the fallback);
the validation data only measure the gap before and after.
"""

from __future__ import annotations

from kohpymc.discovery.augment import augmented_physics
from kohpymc.discovery.evidence import TermSelection, log_bayes_factor
from kohpymc.discovery.fallback import ard_relevance, check_closed_form
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
    "ard_relevance",
    "check_closed_form",
]
