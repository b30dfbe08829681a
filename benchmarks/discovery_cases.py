"""The hidden-effect cases of the discovery benchmark (:mod:`benchmarks.discovery`).

Each case: a physics model (numpy, with its Jacobian) that misses one effect, the truth
that adds it, how calibration and validation inputs are drawn (validation extrapolates
a little), every recorded input (some irrelevant by construction), the inputs the
missing effect depends on, and the true parameters.  ``effect`` is the missing effect
alone (truth minus the model at the true parameters), used for the noise level and to
decide whether an explanation has the true form.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from kohpymc.physics import PhysicsModel
from kohpymc.priors import Uniform

__all__ = ["CASES", "NULLS", "Case"]

Inputs = dict[str, np.ndarray]


@dataclass(frozen=True)
class Case:
    """One hidden effect (or none, for a null case)."""

    name: str
    form: str  # the kind of missing effect, for the table
    physics: Callable[[], PhysicsModel]
    theta: dict[str, float]
    truth: Callable[[Inputs], np.ndarray]  # noiseless output
    draw: Callable[[np.random.Generator, bool], Inputs]  # (rng, validation?) -> inputs
    depends_on: frozenset[str]

    def effect(self, x: Inputs) -> np.ndarray:
        """The missing effect: truth minus the model at the true parameters."""
        return self.truth(x) - self.physics().evaluate(x, self.theta)


def _linear(name: str, inputs: list[str], on: str = "x", lo=0.5, hi=50.0) -> Callable:
    """y = a · x (a the one parameter)."""

    def make():
        return PhysicsModel(
            lambda x, p: p["a"] * x[on], {"a": Uniform(lo, hi)}, inputs,
            jacobian=lambda x, p: np.c_[x[on]], name=name,
        )  # fmt: skip

    return make


def _u(rng, lo, hi, n):
    return rng.uniform(lo, hi, n)


def _free_fall():
    return PhysicsModel(
        lambda x, p: 0.5 * p["g"] * x["t"] ** 2, {"g": Uniform(5.0, 15.0)}, ["t", "m"],
        jacobian=lambda x, p: np.c_[0.5 * x["t"] ** 2], name="free fall",
    )  # fmt: skip


def _drag_truth(x):
    k = 0.5 / x["m"]
    return 9.81 / k * x["t"] - 9.81 / k**2 * (1 - np.exp(-k * x["t"]))


def _drag_draw(rng, val):
    n = 16 if val else 40
    t = _u(rng, 2.0, 2.6, n) if val else _u(rng, 0.2, 2.0, n)
    return {"t": t, "m": _u(rng, 1.0, 8.0, n), "H": _u(rng, 20, 80, n)}


def _ohm():
    return PhysicsModel(
        lambda x, p: p["R"] * x["I"], {"R": Uniform(1.0, 100.0)}, ["I", "T", "H"],
        jacobian=lambda x, p: np.c_[x["I"]], name="Ohm",
    )  # fmt: skip


def _ohm_draw(rng, val):
    n = 16 if val else 40
    T = _u(rng, 50, 60, n) if val else _u(rng, 15, 45, n)
    return {"I": _u(rng, 0.1, 1.0, n), "T": T, "H": _u(rng, 30, 70, n)}


def _decay():
    def f(x, p):
        return p["a"] * np.exp(-p["lam"] * x["t"])

    def jac(x, p):
        e = np.exp(-p["lam"] * x["t"])
        return np.c_[e, -p["a"] * x["t"] * e]

    return PhysicsModel(f, {"a": Uniform(1, 20), "lam": Uniform(0.01, 2.0)}, ["t", "T", "P"],
                        jacobian=jac, name="first-order decay")  # fmt: skip


def _decay_draw(rng, val):
    n = 16 if val else 48
    T = _u(rng, 40, 45, n) if val else _u(rng, 10, 35, n)
    return {"t": _u(rng, 0.0, 5.0, n), "T": T, "P": _u(rng, 0.9, 1.1, n)}


def _pendulum():
    def f(x, p):
        return 2 * np.pi * np.sqrt(x["L"] / p["g"])

    return PhysicsModel(
        f, {"g": Uniform(5.0, 15.0)}, ["L", "A", "M"],
        jacobian=lambda x, p: np.c_[-np.pi * np.sqrt(x["L"]) * p["g"] ** -1.5],
        name="small-angle pendulum",
    )  # fmt: skip


def _pendulum_draw(rng, val):
    n = 16 if val else 40
    A = _u(rng, 0.6, 0.8, n) if val else _u(rng, 0.05, 0.6, n)
    return {"L": _u(rng, 0.2, 2.0, n), "A": A, "M": _u(rng, 0.1, 1.0, n)}


def _draw(spec: dict[str, tuple[float, float]], extrapolate: dict[str, tuple[float, float]]):
    """Uniform inputs; on validation rows ``extrapolate`` replaces the ranges given."""

    def draw(rng, val):
        n = 16 if val else 40
        ranges = {**spec, **(extrapolate if val else {})}
        return {k: _u(rng, lo, hi, n) for k, (lo, hi) in ranges.items()}

    return draw


def _case(name, form, physics, theta, extra, draw, depends_on):
    def truth(x, physics=physics, theta=theta, extra=extra):
        return physics().evaluate(x, theta) + extra(x)

    return Case(name, form, physics, theta, truth, draw, frozenset(depends_on))


_XZ = _draw({"x": (0.5, 5.0), "z": (1.0, 4.0), "w": (0.0, 1.0)}, {"x": (5.0, 6.5)})

CASES: list[Case] = [
    Case(
        "falling body, linear drag",
        "drag t^3/m (exact)",
        _free_fall,
        {"g": 9.81},
        _drag_truth,
        _drag_draw,
        frozenset({"t", "m"}),
    ),
    _case(
        "pipe, ratio Q^2/D",
        "ratio",
        _linear("laminar", ["Q", "D", "T"], "Q"),
        {"a": 3.0},
        lambda x: 0.8 * x["Q"] ** 2 / x["D"],
        _draw({"Q": (0.5, 4.0), "D": (0.5, 2.0), "T": (10, 30)}, {"Q": (4.0, 5.0)}),
        {"Q", "D"},
    ),
    _case(
        "negative power 1/z",
        "negative power",
        _linear("linear", ["x", "z", "w"]),
        {"a": 2.0},
        lambda x: 3.0 / x["z"],
        _XZ,
        {"z"},
    ),
    _case(
        "fractional power sqrt(x)",
        "fractional power",
        _linear("linear", ["x", "z", "w"]),
        {"a": 2.0},
        lambda x: 2.0 * np.sqrt(x["x"]),
        _XZ,
        {"x"},
    ),
    _case(
        "radiation T^4",
        "fourth power",
        _linear("convection", ["T", "RH"], "T", 0.0, 10.0),
        {"a": 2.0},
        lambda x: 5.67e-8 * 0.8 * x["T"] ** 4,
        _draw({"T": (300.0, 400.0), "RH": (20, 80)}, {"T": (400.0, 440.0)}),
        {"T"},
    ),
    _case(
        "three-input product x*z*w",
        "three-input product",
        _linear("linear", ["x", "z", "w", "v"]),
        {"a": 2.0},
        lambda x: 0.6 * x["x"] * x["z"] * x["w"],
        _draw({"x": (0.5, 5.0), "z": (1.0, 4.0), "w": (0.5, 2.0), "v": (0, 1)}, {"x": (5.0, 6.5)}),
        {"x", "z", "w"},
    ),
    _case(
        "saturation S/(1+S/3)",
        "saturation",
        _linear("linear uptake", ["S", "T"], "S"),
        {"a": 1.0},
        lambda x: 2.0 * x["S"] / (1 + x["S"] / 3.0),
        _draw({"S": (0.0, 10.0), "T": (15, 35)}, {"S": (10.0, 14.0)}),
        {"S"},
    ),
    _case(
        "threshold max(0,F-6)",
        "threshold",
        _linear("Hooke", ["F", "T"], "F", 0.01, 1.0),
        {"a": 0.1},
        lambda x: 0.3 * np.maximum(0.0, x["F"] - 6.0),
        _draw({"F": (0.5, 10.0), "T": (15, 35)}, {"F": (10.0, 12.0)}),
        {"F"},
    ),
    _case(
        "decay exp(-t/15)",
        "decay",
        _linear("bridge", ["t", "L", "H"], "L", 0.1, 5.0),
        {"a": 1.2},
        lambda x: 0.8 * np.exp(-x["t"] / 15.0),
        _draw({"t": (0.0, 60.0), "L": (1.0, 5.0), "H": (30, 70)}, {"L": (5.0, 6.0)}),
        {"t"},
    ),
    _case(
        "resistance drifts with T",
        "parameter drift (linear)",
        _ohm,
        {"R": 10.0},
        lambda x: x["I"] * 10.0 * 0.004 * (x["T"] - 20.0),
        _ohm_draw,
        {"I", "T"},
    ),
    Case(
        "decay rate drifts with T",
        "parameter drift (nonlinear model)",
        _decay,
        {"a": 10.0, "lam": 0.5},
        lambda x: 10.0 * np.exp(-0.5 * (1 + 0.01 * (x["T"] - 20.0)) * x["t"]),
        _decay_draw,
        frozenset({"t", "T"}),
    ),
    _case(
        "ignored input H^2",
        "input the model ignores",
        _linear("linear", ["x", "H"]),
        {"a": 2.0},
        lambda x: 0.002 * x["H"] ** 2,
        _draw({"x": (0.5, 5.0), "H": (20.0, 80.0)}, {"x": (5.0, 6.5)}),
        {"H"},
    ),
    _case(
        "multiplicative (1+0.02 T)",
        "multiplicative",
        lambda: PhysicsModel(
            lambda x, p: p["a"] * x["x"] ** 2,
            {"a": Uniform(0.1, 10.0)},
            ["x", "T", "H"],
            jacobian=lambda x, p: np.c_[x["x"] ** 2],
            name="square law",
        ),
        {"a": 1.0},
        lambda x: x["x"] ** 2 * 0.02 * x["T"],
        _draw({"x": (0.5, 4.0), "T": (0.0, 30.0), "H": (30, 70)}, {"x": (4.0, 5.0)}),
        {"x", "T"},
    ),
    _case(
        "logarithm log P",
        "logarithm",
        _linear("linear", ["x", "P"]),
        {"a": 2.0},
        lambda x: 1.5 * np.log(x["P"]),
        _draw({"x": (0.5, 5.0), "P": (0.1, 10.0)}, {"x": (5.0, 6.5)}),
        {"P"},
    ),
    Case(
        "pendulum, finite amplitude",
        "multiplicative (amplitude A^2/16)",
        _pendulum,
        {"g": 9.81},
        lambda x: 2 * np.pi * np.sqrt(x["L"] / 9.81) * (1 + x["A"] ** 2 / 16),
        _pendulum_draw,
        frozenset({"L", "A"}),
    ),
    _case(
        "ratio x/z^2",
        "ratio with a negative power",
        _linear("linear", ["x", "z", "w"]),
        {"a": 2.0},
        lambda x: 1.5 * x["x"] / x["z"] ** 2,
        _XZ,
        {"x", "z"},
    ),
]

#: Null cases: the model is right (data from the physics at the true parameters).
NULLS: list[Case] = [
    Case(
        "null: free fall",
        "null",
        _free_fall,
        {"g": 9.81},
        lambda x: 0.5 * 9.81 * x["t"] ** 2,
        _drag_draw,
        frozenset(),
    ),
    Case("null: Ohm", "null", _ohm, {"R": 10.0}, lambda x: 10.0 * x["I"], _ohm_draw, frozenset()),
    Case(
        "null: decay",
        "null",
        _decay,
        {"a": 10.0, "lam": 0.5},
        lambda x: 10.0 * np.exp(-0.5 * x["t"]),
        _decay_draw,
        frozenset(),
    ),
    Case(
        "null: pendulum",
        "null",
        _pendulum,
        {"g": 9.81},
        lambda x: 2 * np.pi * np.sqrt(x["L"] / 9.81),
        _pendulum_draw,
        frozenset(),
    ),
]
