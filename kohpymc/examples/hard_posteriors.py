"""Small synthetic calibration problems whose posteriors are hard for NUTS in natural units.

Each function returns a :class:`Problem`: a numpy :class:`~kohpymc.PhysicsModel` with an
analytic Jacobian and priors in the user's natural units, synthetic
:class:`~kohpymc.data.CalibrationData` (a fixed design, Gaussian noise drawn with a
given seed), the true parameter values and a sentence on what the data inform.  The
data carry no discrepancy: ``y = G(x; θ_true) + ε``.  By default the noise sd is not
recorded (``noise_sd=None`` in the data, so it is calibrated); pass ``noise_sd=`` to
draw the noise with that sd and record it as known.

The problems are deliberately *not* rescaled: making them easy is the job of the
library, and they are meant for tests and benchmarks of an automatic
reparameterisation.  Posterior summaries quoted below are Laplace approximations with
the noise sd known (``tests/test_examples_hard_posteriors.py``).

* :func:`linear`: ``y = a x``, one parameter; the easy reference.
* :func:`arrhenius`: ``ln k = ln A - E_a / (R T)`` with ``A ≈ 1e13`` 1/s and
  ``E_a ≈ 1.2e5`` J/mol: scales twelve orders of magnitude apart and the classic
  compensation between ``A`` and ``E_a`` (posterior correlation ≈ 0.996).
* :func:`collinear`: ``y = a x + b x^1.1`` on ``x ∈ [1, 2]``: nearly collinear
  sensitivities, posterior correlation ≈ -0.9998 between proper Normal priors.
* :func:`multiplicative`: ``y = k c x``: the data inform only the product ``k c``;
  ``k`` and ``c`` are separated only by their priors.  In ``(k, c)`` the posterior is a
  thin curved ridge along the hyperbola ``k c = const`` (a banana), in
  ``(log k, log c)`` a straight one.

:func:`all_problems` returns the four by name.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from kohpymc.data import CalibrationData
from kohpymc.physics import PhysicsModel
from kohpymc.priors import LogNormal, Normal

__all__ = [
    "GAS_CONSTANT",
    "Problem",
    "linear",
    "linear_model",
    "linear_jacobian",
    "arrhenius",
    "arrhenius_log_rate",
    "arrhenius_log_rate_jacobian",
    "collinear",
    "collinear_model",
    "collinear_jacobian",
    "multiplicative",
    "multiplicative_model",
    "multiplicative_jacobian",
    "all_problems",
]

#: J/(mol K), the molar gas constant R (exact since the 2019 SI)
GAS_CONSTANT = 8.314462618

#: exponent of the second term of :func:`collinear`
_COLLINEAR_POWER = 1.1


@dataclass(frozen=True)
class Problem:
    """One synthetic calibration problem.

    Attributes
    ----------
    name : str
        Short name, the key in :func:`all_problems`.
    physics : PhysicsModel
        The model ``G(x; θ)`` (numpy, analytic Jacobian) with priors in natural units.
    data : CalibrationData
        Synthetic measurements ``G(x; θ_true) + ε``; its inputs are exactly the model's.
    truth : dict
        The true value of every physics parameter.
    description : str
        What the problem is and why its posterior is hard.
    informed : str
        What the data inform, in words (e.g. ``"k*c"``).
    true_noise_sd : float
        The sd the noise was drawn with (recorded in ``data`` only if ``noise_sd=``
        was given).

    Examples
    --------
    >>> problem = linear()
    >>> problem.name, problem.physics.parameter_names, problem.data.noise_sd
    ('linear', ('a',), None)
    """

    name: str
    physics: PhysicsModel
    data: CalibrationData
    truth: dict[str, float]
    description: str
    informed: str
    true_noise_sd: float


def _make(
    name: str,
    physics: PhysicsModel,
    inputs: dict[str, np.ndarray],
    truth: dict[str, float],
    *,
    default_sd: float,
    noise_sd: float | None,
    seed: int,
    output_name: str,
    description: str,
    informed: str,
) -> Problem:
    sd = default_sd if noise_sd is None else float(noise_sd)
    if not (math.isfinite(sd) and sd > 0):
        raise ValueError(f"noise_sd must be a positive finite number, got {noise_sd!r}")
    rng = np.random.default_rng(seed)
    clean = physics.evaluate(inputs, truth)
    y = clean + rng.normal(0.0, sd, size=clean.size)
    data = CalibrationData(inputs, y, noise_sd=noise_sd, output_name=output_name)
    return Problem(name, physics, data, dict(truth), description, informed, sd)


# ------------------------------------------------------------------------------- linear
def linear_model(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
    """``y = a x``.

    Examples
    --------
    >>> linear_model({"x": np.array([0.0, 1.0])}, {"a": 2.5})
    array([0. , 2.5])
    """
    return params["a"] * np.asarray(inputs["x"], dtype=float)


def linear_jacobian(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """``∂y/∂a = x``.

    Examples
    --------
    >>> linear_jacobian({"x": np.array([0.5])}, {"a": 2.5})["a"]
    array([0.5])
    """
    return {"a": np.asarray(inputs["x"], dtype=float).copy()}


def linear(seed: int = 0, *, noise_sd: float | None = None) -> Problem:
    """The easy reference: ``y = a x``, ``a ~ Normal(2, 1)``, truth ``a = 2.5``.

    20 equally spaced ``x`` in ``[0, 1]``, noise sd 0.1 (posterior sd of ``a`` ≈ 0.04).

    Parameters
    ----------
    seed : int
        Seed of the noise.
    noise_sd : float, optional
        Draw the noise with this sd and record it as known; default: sd 0.1, unknown.

    Returns
    -------
    Problem

    Examples
    --------
    >>> problem = linear(seed=1)
    >>> problem.data.n, problem.truth, problem.informed
    (20, {'a': 2.5}, 'a')
    """
    physics = PhysicsModel(
        linear_model,
        {"a": Normal(2.0, 1.0)},
        inputs=["x"],
        jacobian=linear_jacobian,
        name="linear",
    )
    return _make(
        "linear",
        physics,
        {"x": np.linspace(0.0, 1.0, 20)},
        {"a": 2.5},
        default_sd=0.1,
        noise_sd=noise_sd,
        seed=seed,
        output_name="y",
        description=(
            "y = a x on x in [0, 1] with a ~ Normal(2, 1): one well-identified parameter "
            "of order one, the easy reference."
        ),
        informed="a",
    )


# ---------------------------------------------------------------------------- arrhenius
def arrhenius_log_rate(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
    """Natural log of the Arrhenius rate, ``ln k = ln A - E_a / (R T)``.

    Parameters
    ----------
    inputs : mapping
        ``T``: temperatures (K).
    params : mapping
        ``A``: pre-exponential factor (1/s); ``Ea``: activation energy (J/mol).

    Returns
    -------
    numpy.ndarray
        ``ln k`` with ``k`` in 1/s.

    Examples
    --------
    >>> T = np.array([300.0, 400.0])
    >>> np.round(arrhenius_log_rate({"T": T}, {"A": 1e13, "Ea": 1.2e5}), 3)
    array([-18.175,  -6.148])
    """
    T = np.asarray(inputs["T"], dtype=float)
    return np.log(params["A"]) - params["Ea"] / (GAS_CONSTANT * T)


def arrhenius_log_rate_jacobian(
    inputs: Mapping[str, Any], params: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """``∂ln k/∂A = 1/A`` and ``∂ln k/∂E_a = -1/(R T)``.

    Examples
    --------
    >>> J = arrhenius_log_rate_jacobian({"T": np.array([300.0])}, {"A": 1e13, "Ea": 1.2e5})
    >>> float(J["A"][0]), round(float(J["Ea"][0]), 8)
    (1e-13, -0.00040091)
    """
    T = np.asarray(inputs["T"], dtype=float)
    return {"A": np.full(T.shape, 1.0 / params["A"]), "Ea": -1.0 / (GAS_CONSTANT * T)}


def arrhenius(seed: int = 0, *, noise_sd: float | None = None) -> Problem:
    """Arrhenius kinetics: ``ln k(T) = ln A - E_a / (R T)``, parameters in SI units.

    Rate constants (1/s) of a first-order reaction are measured at 30 equally spaced
    temperatures in 300–400 K and reported as ``ln k`` (from about -18 to -6); the
    noise sd 0.1 on ``ln k`` is a 10 % relative scatter of ``k``.  The output is the log
    rate because the library's noise is additive and Gaussian; on ``k`` itself the
    multiplicative scatter would not be.  Truth ``A = 1e13`` 1/s (about ``k_B T / h``),
    ``E_a = 1.2e5`` J/mol.

    Priors: ``A ~ LogNormal(ln 1e12, 2 ln 10)`` (median 1e12 1/s, two decades sd) and
    ``E_a ~ Normal(1e5, 3e4)`` J/mol.  The data fix the rate near the middle of the
    temperature range, so a larger ``A`` is compensated by a larger ``E_a``: the
    posterior correlation of ``(A, E_a)`` is ≈ 0.996, with sd ≈ 2e12 1/s and
    ≈ 600 J/mol, some nine orders of magnitude apart.

    Parameters
    ----------
    seed : int
        Seed of the noise.
    noise_sd : float, optional
        Draw the noise with this sd (on ``ln k``) and record it as known; default: sd
        0.1, unknown.

    Returns
    -------
    Problem

    Examples
    --------
    >>> problem = arrhenius()
    >>> problem.data.n, problem.data.input_names, problem.data.output_name
    (30, ('T',), 'ln_k')
    """
    physics = PhysicsModel(
        arrhenius_log_rate,
        {"A": LogNormal(math.log(1e12), 2.0 * math.log(10.0)), "Ea": Normal(1.0e5, 3.0e4)},
        inputs=["T"],
        jacobian=arrhenius_log_rate_jacobian,
        name="arrhenius",
    )
    return _make(
        "arrhenius",
        physics,
        {"T": np.linspace(300.0, 400.0, 30)},
        {"A": 1.0e13, "Ea": 1.2e5},
        default_sd=0.1,
        noise_sd=noise_sd,
        seed=seed,
        output_name="ln_k",
        description=(
            "ln k = ln A - Ea/(R T) at T in 300-400 K with A ~ 1e13 1/s and Ea ~ 1.2e5 J/mol "
            "in SI units: scales nine orders of magnitude apart and the Arrhenius "
            "compensation between A and Ea (posterior correlation about 0.996)."
        ),
        informed="the rate ln k over 300-400 K, i.e. Ea and ln A with a strong positive "
        "correlation (ln A - Ea/(R T) at T about 345 K is well determined)",
    )


# ---------------------------------------------------------------------------- collinear
def collinear_model(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
    """``y = a x + b x^1.1``.

    Examples
    --------
    >>> collinear_model({"x": np.array([1.0])}, {"a": 1.0, "b": 2.0})
    array([3.])
    """
    x = np.asarray(inputs["x"], dtype=float)
    return params["a"] * x + params["b"] * x**_COLLINEAR_POWER


def collinear_jacobian(
    inputs: Mapping[str, Any], params: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """``∂y/∂a = x``, ``∂y/∂b = x^1.1``.

    Examples
    --------
    >>> J = collinear_jacobian({"x": np.array([1.0, 2.0])}, {"a": 1.0, "b": 2.0})
    >>> J["a"], np.round(J["b"], 4)
    (array([1., 2.]), array([1.    , 2.1435]))
    """
    x = np.asarray(inputs["x"], dtype=float)
    return {"a": x.copy(), "b": x**_COLLINEAR_POWER}


def collinear(seed: int = 0, *, noise_sd: float | None = None) -> Problem:
    """Nearly collinear sensitivities: ``y = a x + b x^1.1`` on ``x ∈ [1, 2]``.

    Two power-law terms with close exponents, as in a constitutive law fitted with one
    term too many.  Over ``[1, 2]`` the sensitivities ``x`` and ``x^1.1`` are almost
    proportional, so the data fix ``a + b`` (roughly) and only weakly the split.  30
    equally spaced ``x``, noise sd 0.05, truth ``a = 1``, ``b = 2``, priors
    ``a, b ~ Normal(1.5, 1)``.  The posterior correlation is ≈ -0.9998 with sd ≈ 0.3
    for each: the data (not only the priors) identify both, along a ridge about 100
    times longer than wide.

    Parameters
    ----------
    seed : int
        Seed of the noise.
    noise_sd : float, optional
        Draw the noise with this sd and record it as known; default: sd 0.05, unknown.

    Returns
    -------
    Problem

    Examples
    --------
    >>> problem = collinear()
    >>> problem.physics.parameter_names, problem.truth
    (('a', 'b'), {'a': 1.0, 'b': 2.0})
    """
    physics = PhysicsModel(
        collinear_model,
        {"a": Normal(1.5, 1.0), "b": Normal(1.5, 1.0)},
        inputs=["x"],
        jacobian=collinear_jacobian,
        name="collinear",
    )
    return _make(
        "collinear",
        physics,
        {"x": np.linspace(1.0, 2.0, 30)},
        {"a": 1.0, "b": 2.0},
        default_sd=0.05,
        noise_sd=noise_sd,
        seed=seed,
        output_name="y",
        description=(
            "y = a x + b x^1.1 on x in [1, 2]: nearly collinear sensitivities, posterior "
            "correlation about -0.9998 between proper Normal(1.5, 1) priors."
        ),
        informed="a + b well (the combination a x + b x^1.1), a and b separately only weakly",
    )


# ----------------------------------------------------------------------- multiplicative
def multiplicative_model(inputs: Mapping[str, Any], params: Mapping[str, Any]) -> np.ndarray:
    """``y = k c x``.

    Examples
    --------
    >>> multiplicative_model({"x": np.array([0.5])}, {"k": 2.0, "c": 5.0})
    array([5.])
    """
    return params["k"] * params["c"] * np.asarray(inputs["x"], dtype=float)


def multiplicative_jacobian(
    inputs: Mapping[str, Any], params: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """``∂y/∂k = c x``, ``∂y/∂c = k x``.

    Examples
    --------
    >>> J = multiplicative_jacobian({"x": np.array([0.5])}, {"k": 2.0, "c": 5.0})
    >>> J["k"], J["c"]
    (array([2.5]), array([1.]))
    """
    x = np.asarray(inputs["x"], dtype=float)
    return {"k": params["c"] * x, "c": params["k"] * x}


def multiplicative(seed: int = 0, *, noise_sd: float | None = None) -> Problem:
    """Multiplicative confounding: ``y = k c x``; the data inform only ``k c``.

    For example a response read through an instrument of uncertain gain ``c``: only the
    product of gain and physical coefficient ``k`` reaches the data.  25 equally spaced
    ``x`` in ``[0.1, 1]``, noise sd 0.1, truth ``k = 2``, ``c = 5``, priors
    ``k, c ~ LogNormal(ln 3, 1)``.  The posterior is a thin ridge along ``k c ≈ 10``: a
    hyperbola (banana) in ``(k, c)``, a straight line in ``(ln k, ln c)`` where the sd
    of ``ln(k c)`` is ≈ 0.003 and that of ``ln k`` ≈ 0.7 (set by the priors alone).

    Parameters
    ----------
    seed : int
        Seed of the noise.
    noise_sd : float, optional
        Draw the noise with this sd and record it as known; default: sd 0.1, unknown.

    Returns
    -------
    Problem

    Examples
    --------
    >>> problem = multiplicative()
    >>> problem.informed, problem.truth
    ('k*c', {'k': 2.0, 'c': 5.0})
    """
    prior = LogNormal(math.log(3.0), 1.0)
    physics = PhysicsModel(
        multiplicative_model,
        {"k": prior, "c": prior},
        inputs=["x"],
        jacobian=multiplicative_jacobian,
        name="multiplicative",
    )
    return _make(
        "multiplicative",
        physics,
        {"x": np.linspace(0.1, 1.0, 25)},
        {"k": 2.0, "c": 5.0},
        default_sd=0.1,
        noise_sd=noise_sd,
        seed=seed,
        output_name="y",
        description=(
            "y = k c x with k, c ~ LogNormal(ln 3, 1): the data inform only the product; "
            "the posterior is a thin ridge along k c = 10, curved (a banana) in (k, c) "
            "and straight in (ln k, ln c)."
        ),
        informed="k*c",
    )


# ---------------------------------------------------------------------------------- all
def all_problems(seed: int = 0) -> dict[str, Problem]:
    """The four problems by name, each with unknown noise and the given seed.

    Examples
    --------
    >>> list(all_problems())
    ['linear', 'arrhenius', 'collinear', 'multiplicative']
    """
    return {
        problem.name: problem
        for problem in (linear(seed), arrhenius(seed), collinear(seed), multiplicative(seed))
    }
