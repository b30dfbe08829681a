"""The result of :func:`kohpymc.discovery.discover`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from kohpymc.discovery.evidence import TermSelection

__all__ = ["DiscoveryReport", "explanations"]


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
    closed_form_check : dict or None
        The cross-validated check of the most probable closed form
        (:meth:`kohpymc.discovery.fallback.ClosedFormCheck.to_dict`; None when nothing
        closed-form was significant).
    fallback : dict or None
        When no closed form was found: ``{"formulation": "gp", "inputs", "reason",
        "log_ml_drop", "range_over_length_scale", "length_scale_over_range"}``; ``effect``
        then reads ``"depends on t and m; no closed form found"``.
    formulation : Discrepancy or None
        The discrepancy of the "after" calibration (the GP of the fallback), else None.
    units : dict or None
        With units given: ``{"given": {name: SI text}, "pi_groups": [...],
        "coefficients": {term name: unit of its coefficient}, "offset": unit of c_0}``.
    theta : dict or None
        Where θ came from when it was borrowed from a joint calibration of several
        outputs (:func:`kohpymc.multi_output.discover_outputs`): ``{"source",
        "outputs", "borrowed_from", "values", "sd", ...}``; None (and absent from the
        JSON) when θ was calibrated from this output alone.
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
    closed_form_check: dict | None = None
    fallback: dict | None = None
    formulation: Any = None
    units: dict | None = None
    theta: dict | None = None

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
        sel = self.selection
        out = {
            "significant": self.significant,
            "effect": self.effect,
            "inputs": list(self.inputs),
            "where": self.where,
            "validation": self.validation,
            "parameters": self.parameters,
            "parameters_sd": self.parameters_sd,
            "criterion": {
                "probability_nothing_missing": sel.probability_none,
                "p_value": sel.p_value,
                "false_alarm_rate": self.threshold,
                "threshold": self.threshold,
            },
            "explanations": explanations(sel, units=self.units),
            "closed_form_found": self.significant and self.fallback is None,
            "closed_form_check": self.closed_form_check,
            "fallback": self.fallback,
            "units": self._units(),
            "input_probability": self.input_probability,
            "rejected_candidates": sel.rejected,
            "merged_candidates": len(sel.merged),
            "top_subsets": [{"terms": list(s), "probability": p} for s, p in sel.subsets[:5]],
        }
        if self.theta is not None:
            out["theta"] = self.theta
        return out

    def _units(self) -> dict | None:
        """The units summary with ``c_k`` of the added terms (and ``c_0``) spelled out."""
        if self.units is None:
            return None
        out = dict(self.units)
        if self.significant and self.fallback is None and self.physics is not None:
            names = [n for n in self.physics.parameters if n.startswith("c_")]
            best = next((s for s, _ in self.selection.subsets if s), ())
            terms = [n for n in best if n != "1"]
            coef = {f"c_{k + 1}": out["coefficients"].get(n) for k, n in enumerate(terms)}
            if "c_0" in names:
                coef["c_0"] = out.get("offset")
            out["fitted"] = {k: v for k, v in coef.items() if k in names}
        return out


def _describe(sel: TermSelection, subset: tuple[str, ...]) -> dict:
    if not subset:
        return {"terms": [], "expression": "nothing missing", "inputs": [], "meaning": []}
    terms = [sel.terms.get(n) for n in subset if n != "1"]
    pieces = [t.expression if t is not None else f"c * {n}"
              for n, t in zip([n for n in subset if n != "1"], terms, strict=True)]  # fmt: skip
    if sel.constant:
        pieces.append("c_0")
    inputs = list(dict.fromkeys(i for t in terms if t is not None for i in t.inputs))
    meaning = [t.meaning or f"an additive term {t.name} in {', '.join(t.inputs)}"
               for t in terms if t is not None]  # fmt: skip
    return {
        "terms": list(subset),
        "expression": " + ".join(pieces) if terms else "c_0 (a constant offset)",
        "inputs": inputs,
        "meaning": meaning if terms else ["a constant offset"],
    }


def explanations(sel: TermSelection, top: int = 10, units: dict | None = None) -> list[dict]:
    """The ``top`` explanations with their posterior probabilities (and "nothing missing").

    With ``units`` (:attr:`DiscoveryReport.units`) each explanation also lists the unit
    of each coefficient (``"coefficient_units"``, the constant's last).

    Examples
    --------
    >>> sel = TermSelection((), 0.9, {}, [((), 0.9), (("1",), 0.1)])
    >>> [(e["expression"], e["probability"]) for e in explanations(sel)]
    [('nothing missing', 0.9), ('c_0 (a constant offset)', 0.1)]
    """
    ranked = list(sel.subsets[:top])
    if not any(not s for s, _ in ranked):
        ranked.append(((), sel.probability_none))
    out = []
    for subset, p in ranked:
        entry = _describe(sel, subset)
        entry["probability"] = float(p)
        entry["log_bayes_factor"] = sel.log_bayes_factors.get(subset)
        if units is not None and subset:
            coef = units["coefficients"]
            entry["coefficient_units"] = [coef.get(n) for n in subset if n != "1"]
            if sel.constant:
                entry["coefficient_units"].append(units.get("offset"))
        out.append(entry)
    return out
