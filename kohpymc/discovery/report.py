"""The result of :func:`kohpymc.discovery.discover`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from kohpymc.discovery.evidence import TermSelection

__all__ = ["DiscoveryReport"]


@dataclass
class DiscoveryReport:
    """What :func:`discover` found and did.

    Attributes
    ----------
    significant : bool
        Whether a missing effect was found (posterior probability of "nothing missing"
        below ``threshold``).
    effect : str or None
        The added term(s), e.g. ``"c * x * P"``.
    inputs : list of str
        Inputs the added term depends on.
    where : list of dict
        Ranges of the named inputs where the model as given fails
        (``{"input", "from", "to", "data", "rows"}``, see :func:`discover`).
    validation : dict
        ``{"before": {...}, "after": {...}}`` with ``mu_r``, ``mu_r_mcse``, ``rmse``,
        ``coverage90``.
    parameters, parameters_sd : dict
        Posterior means and sds of the parameters before and after.
    selection : TermSelection
        The term comparison.
    input_probability : dict input -> float
        Posterior probability that the missing effect depends on each input.
    threshold : float
        The significance threshold used.
    physics : PhysicsModel
        The augmented model (the original one when nothing is missing).
    before, after : InferenceData
        Calibrations with predictions at the validation inputs.
    key_input : str
        The input along which the added term (before: the squared residual) varies most
        (largest first-order variance share), for plotting.
    residuals : dict
        ``{"before": array, "after": array}``: calibration residuals from the
        posterior-mean model.
    """

    significant: bool
    effect: str | None
    inputs: list[str]
    where: list[dict]
    validation: dict
    parameters: dict
    parameters_sd: dict
    selection: TermSelection
    input_probability: dict
    threshold: float
    physics: Any
    before: Any
    after: Any
    key_input: str
    residuals: dict

    def to_dict(self) -> dict:
        """The JSON report.

        Examples
        --------
        >>> sel = TermSelection((), 0.9, {}, [((), 0.9)])
        >>> r = DiscoveryReport(False, None, [], [], {}, {}, {}, sel, {}, 0.01, None,
        ...                     None, None, "x", {})
        >>> r.to_dict()["significant"], r.to_dict()["effect"]
        (False, None)
        """
        return {
            "significant": self.significant,
            "effect": self.effect,
            "inputs": list(self.inputs),
            "where": self.where,
            "validation": self.validation,
            "parameters": self.parameters,
            "parameters_sd": self.parameters_sd,
            "criterion": {
                "probability_nothing_missing": self.selection.probability_none,
                "threshold": self.threshold,
            },
            "input_probability": self.input_probability,
            "rejected_candidates": self.selection.rejected,
            "top_subsets": [
                {"terms": list(s), "probability": p} for s, p in self.selection.subsets[:5]
            ],
        }
