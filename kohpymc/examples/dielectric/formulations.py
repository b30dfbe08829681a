"""The discrepancy formulations M0–M5 of the example, with the Eq. (29) mean and variance."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import pytensor.tensor as pt

from kohpymc.examples.dielectric.constants import T_END
from kohpymc.priors import Normal

if TYPE_CHECKING:
    from kohpymc.discrepancy import Discrepancy, ParametricFunction

#: fixed input scales of the Eq. (29) forms (scaling, not centring, keeps the form)
_V_REF, _T_REF = 25.0, 345.0


def _eq29(values: Mapping[str, Any], p: Mapping[str, Any], offset: bool) -> Any:
    out = (
        p["phi1"] * values["V"] / _V_REF
        + p["phi2"] * values["T"] / _T_REF
        + p["phi3"] * values["t"] / T_END
        + p["phi4"] * pt.exp(p["phi5"] * values["t"] / T_END)
    )
    return out + p["phi0"] if offset else out


def eq29_mean(scale: float = 20.0) -> ParametricFunction:
    """The mean of Eq. (29): ``φ1 V' + φ2 T' + φ3 t' + φ4 exp(φ5 t')``, no constant term.

    ``V' = V / 25 V``, ``T' = T / 345 K``, ``t' = t / 100 s`` (pure rescalings, so the
    functional form is exactly the paper's).  Priors ``φ1..φ4 ~ Normal(0, scale)``
    (nA/cm²), ``φ5 ~ Normal(-5, 2.5)`` (decay times of order 20 s).  Parameters are
    named ``delta_mean_phi1`` ... in the model.

    Examples
    --------
    >>> sorted(eq29_mean().parameters)
    ['phi1', 'phi2', 'phi3', 'phi4', 'phi5']
    """
    from kohpymc.discrepancy import ParametricFunction

    priors = {f"phi{k}": Normal(0.0, scale) for k in range(1, 5)}
    priors["phi5"] = Normal(-5.0, 2.5)
    return ParametricFunction(
        lambda v, p: _eq29(v, p, offset=False), priors, inputs=["V", "T", "t"]
    )


def eq29_log_variance(scale: float = 20.0) -> ParametricFunction:
    """The variance of Eq. (29), ``ϕ0 + ϕ1 V' + ϕ2 T' + ϕ3 t' + ϕ4 exp(ϕ5 t')``, as ``g``.

    Used with ``link="softplus"``: ``σ_δ² = log(1 + exp(g))`` equals the paper's linear
    form wherever it exceeds a few (nA/cm²)² and stays positive elsewhere (the paper's
    form can turn negative).  Priors ``ϕ0..ϕ4 ~ Normal(0, scale²)``, ``ϕ5 ~ Normal(-5,
    2.5)``; parameters ``delta_logvar_phi0`` ... in the model.

    Examples
    --------
    >>> sorted(eq29_log_variance().parameters)[:2]
    ['phi0', 'phi1']
    """
    from kohpymc.discrepancy import ParametricFunction

    priors = {f"phi{k}": Normal(0.0, scale**2) for k in range(0, 5)}
    priors["phi5"] = Normal(-5.0, 2.5)
    return ParametricFunction(lambda v, p: _eq29(v, p, offset=True), priors, inputs=["V", "T", "t"])


def formulations(scale: float = 20.0) -> dict[str, Discrepancy]:
    """The paper's formulations M0–M5 for this example.

    M3 uses the Eq. (29) mean and (softplus-linked) variance; M4 (stationary SE kernel
    over V, T, t) and M5 (Eq. 14 kernel, decaying in t) use the same mean.  ``scale``
    (nA/cm²) sizes the priors of the Eq. (29) coefficients.  All settings share one
    time grid, so M5's decaying term ``w1 exp(-w2 t) 1[t = t']`` also couples the 12
    settings at equal times, as Eq. (14) is written.  At the prior mean ``φ4 = 0`` and
    ``φ5`` has no effect: run identifiability checks at a point with ``φ4 != 0``.

    Examples
    --------
    >>> {k: v.label for k, v in formulations().items()}["M5"]
    'M5'
    """
    from kohpymc.discrepancy import (
        ConstantBias,
        GaussianProcess,
        IIDGaussian,
        InputDependentGaussian,
        NoDiscrepancy,
        NonStationaryGP,
    )

    inputs = ["V", "T", "t"]
    return {
        "M0": NoDiscrepancy(),
        "M1": ConstantBias(),
        "M2": IIDGaussian(),
        "M3": InputDependentGaussian(
            mean=eq29_mean(scale), log_variance=eq29_log_variance(scale), link="softplus"
        ),
        "M4": GaussianProcess(inputs, mean=eq29_mean(scale)),
        "M5": NonStationaryGP(inputs, time="t", mean=eq29_mean(scale)),
    }
