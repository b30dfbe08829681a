"""Prior distributions for named parameters.

A :class:`Prior` is a small, validated description of a PyMC distribution that knows
its support, its mean (the paper's default Taylor expansion point, Section 4) and a
typical magnitude (used to size finite-difference steps).  The factories
:func:`Uniform`, :func:`LogUniform`, :func:`Normal`, :func:`LogNormal`, :func:`HalfNormal`
cover the common cases (:func:`LogUniform` for a positive parameter known only to within
orders of magnitude, such as a rate constant or a trap density); :func:`Custom` accepts
any PyMC distribution factory as an escape hatch.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pymc as pm
import pytensor.tensor as pt
from pymc.distributions.transforms import Interval

__all__ = [
    "Prior",
    "Uniform",
    "LogUniform",
    "Normal",
    "LogNormal",
    "HalfNormal",
    "Custom",
    "as_prior",
]


@dataclass(frozen=True)
class Prior:
    """A prior for one scalar parameter.

    Parameters
    ----------
    kind : str
        One of ``"uniform"``, ``"loguniform"``, ``"normal"``, ``"lognormal"``,
        ``"halfnormal"``, ``"custom"``.
    args : dict
        Distribution arguments (``lower``/``upper``, ``mu``/``sigma``, ...).
    factory : callable, optional
        For ``kind="custom"``: ``factory(name, **kwargs)`` returning a PyMC random variable.
    mean_value, typical : float, optional
        For custom priors, a representative value and magnitude (defaults 0 and 1).

    Examples
    --------
    >>> from kohpymc import Uniform
    >>> Uniform(50.0, 300.0).mean()
    175.0
    """

    kind: str
    args: dict[str, float] = field(default_factory=dict)
    factory: Callable[..., Any] | None = None
    mean_value: float | None = None
    typical: float | None = None

    def create(self, name: str, **kwargs: Any):
        """Create the PyMC random variable ``name`` in the current model context."""
        a = self.args
        if self.kind == "uniform":
            return pm.Uniform(name, lower=a["lower"], upper=a["upper"], **kwargs)
        if self.kind == "loguniform":
            return _log_uniform(name, a["lower"], a["upper"], **kwargs)
        if self.kind == "normal":
            return pm.Normal(name, mu=a["mu"], sigma=a["sigma"], **kwargs)
        if self.kind == "lognormal":
            return pm.LogNormal(name, mu=a["mu"], sigma=a["sigma"], **kwargs)
        if self.kind == "halfnormal":
            return pm.HalfNormal(name, sigma=a["sigma"], **kwargs)
        if self.kind == "custom":
            assert self.factory is not None
            return self.factory(name, **kwargs)
        raise ValueError(f"unknown prior kind {self.kind!r}")  # pragma: no cover

    def mean(self) -> float:
        """Prior mean (the default Taylor-expansion point of the paper, Section 4)."""
        a = self.args
        if self.kind == "uniform":
            return 0.5 * (a["lower"] + a["upper"])
        if self.kind == "loguniform":
            return (a["upper"] - a["lower"]) / math.log(a["upper"] / a["lower"])
        if self.kind == "normal":
            return a["mu"]
        if self.kind == "lognormal":
            return math.exp(a["mu"] + 0.5 * a["sigma"] ** 2)
        if self.kind == "halfnormal":
            return a["sigma"] * math.sqrt(2.0 / math.pi)
        return 0.0 if self.mean_value is None else float(self.mean_value)

    def sd(self) -> float:
        """Prior standard deviation (``scale()`` for custom priors).

        Examples
        --------
        >>> round(Uniform(0.0, 12.0).sd(), 6)
        3.464102
        """
        a = self.args
        if self.kind == "uniform":
            return (a["upper"] - a["lower"]) / math.sqrt(12.0)
        if self.kind == "loguniform":
            second = (a["upper"] ** 2 - a["lower"] ** 2) / (2.0 * math.log(a["upper"] / a["lower"]))
            return math.sqrt(max(second - self.mean() ** 2, 0.0))
        if self.kind == "normal":
            return a["sigma"]
        if self.kind == "lognormal":
            var = (math.exp(a["sigma"] ** 2) - 1.0) * math.exp(2 * a["mu"] + a["sigma"] ** 2)
            return math.sqrt(var)
        if self.kind == "halfnormal":
            return a["sigma"] * math.sqrt(1.0 - 2.0 / math.pi)
        return self.scale()

    def scale(self) -> float:
        """Typical magnitude of the parameter (positive), used for step sizes."""
        a = self.args
        if self.kind == "uniform":
            return max(abs(a["lower"]), abs(a["upper"]), a["upper"] - a["lower"])
        if self.kind == "normal":
            return max(abs(a["mu"]), a["sigma"])
        if self.kind in ("loguniform", "lognormal", "halfnormal"):
            return self.mean()
        return 1.0 if self.typical is None else float(self.typical)

    def quantile(self, q: float) -> float:
        """The prior's ``q`` quantile, ``0 < q < 1`` (custom priors: ``mean + sd·Φ⁻¹(q)``).

        Examples
        --------
        >>> from kohpymc import LogUniform
        >>> float(f"{LogUniform(1e-13, 1e-9).quantile(0.5):.3g}")
        1e-11
        """
        from scipy import stats

        if not 0.0 < q < 1.0:
            raise ValueError(f"quantile: q must be in (0, 1), got {q!r}")
        a = self.args
        if self.kind == "uniform":
            return a["lower"] + q * (a["upper"] - a["lower"])
        if self.kind == "loguniform":
            return a["lower"] * (a["upper"] / a["lower"]) ** q
        if self.kind == "halfnormal":
            return float(stats.halfnorm.ppf(q, scale=a["sigma"]))
        z = float(stats.norm.ppf(q))
        if self.kind == "normal":
            return a["mu"] + a["sigma"] * z
        if self.kind == "lognormal":
            return math.exp(a["mu"] + a["sigma"] * z)
        return self.mean() + self.sd() * z

    def in_support(self, value: float) -> bool:
        """Whether ``value`` lies in the support of the prior."""
        if not math.isfinite(value):
            return False
        if self.kind in ("uniform", "loguniform"):
            return self.args["lower"] <= value <= self.args["upper"]
        if self.kind in ("lognormal", "halfnormal"):
            return value > 0
        return True

    def __repr__(self) -> str:
        inner = ", ".join(f"{k}={v:g}" for k, v in self.args.items())
        return f"{self.kind.capitalize()}({inner})"


def _finite(name: str, **values: float) -> dict[str, float]:
    out = {}
    for key, val in values.items():
        if isinstance(val, str | bytes | bool):
            kind = "true/false" if isinstance(val, bool) else "text"
            raise TypeError(f"{name} prior: {key}={val!r} is {kind}, not a number (unquote it)")
        try:
            fval = float(val)
        except (TypeError, ValueError) as err:
            raise TypeError(f"{name} prior: {key}={val!r} is not a number") from err
        if not math.isfinite(fval):
            raise ValueError(f"{name} prior: {key}={val!r} must be finite")
        out[key] = fval
    return out


def _representable(prior: Prior) -> Prior:
    """``prior`` when its mean, sd and scale are finite floats, else ``ValueError``."""
    try:
        moments: tuple[float, ...] = (prior.mean(), prior.sd(), prior.scale())
    except OverflowError:
        moments = (math.inf,)
    if not all(math.isfinite(m) for m in moments):
        raise ValueError(
            f"{prior.kind} prior {prior!r}: its mean or spread overflows a float (values too large)"
        )
    return prior


def Uniform(lower: float, upper: float) -> Prior:  # noqa: N802 - reads like a distribution
    """Uniform prior on ``[lower, upper]``.

    Examples
    --------
    >>> Uniform(0.0, 1.0).args
    {'lower': 0.0, 'upper': 1.0}
    """
    args = _finite("uniform", lower=lower, upper=upper)
    if not args["lower"] < args["upper"]:
        raise ValueError(f"uniform prior: lower={lower!r} must be < upper={upper!r}")
    return _representable(Prior("uniform", args))


def LogUniform(lower: float, upper: float) -> Prior:  # noqa: N802
    """Log-uniform prior on ``[lower, upper]``, ``0 < lower``: density ∝ 1/value.

    Every decade of the range is equally likely a priori (the natural choice for a
    positive parameter known only to within orders of magnitude).

    Examples
    --------
    >>> p = LogUniform(1e6, 1e10)
    >>> p.in_support(1e8), p.in_support(1e11)
    (True, False)
    """
    args = _finite("loguniform", lower=lower, upper=upper)
    if not 0 < args["lower"] < args["upper"]:
        raise ValueError(f"loguniform prior: need 0 < lower={lower!r} < upper={upper!r}")
    return _representable(Prior("loguniform", args))


def _log_uniform_logp(value, lower, upper):
    inside = pt.and_(pt.ge(value, lower), pt.le(value, upper))
    return pt.switch(inside, -pt.log(value) - pt.log(pt.log(upper) - pt.log(lower)), -np.inf)


def _log_uniform_random(lower, upper, rng=None, size=None):
    return np.exp(rng.uniform(np.log(lower), np.log(upper), size=size))


def _log_uniform(name: str, lower: float, upper: float, **kwargs: Any):
    """A log-uniform random variable (a ``CustomDist``: PyMC has none).

    It has the interval transform (the unconstrained space of ``pm.Uniform``) and the
    geometric mean of the bounds as its initial point.
    """
    # float64 bounds: PyTensor types a Python float that float32 holds exactly as float32
    return pm.CustomDist(
        name,
        np.float64(lower),
        np.float64(upper),
        logp=_log_uniform_logp,
        random=_log_uniform_random,
        support_point=lambda rv, size, lo, hi: pt.full_like(rv, pt.sqrt(lo * hi)),
        transform=Interval(lower, upper),
        **kwargs,
    )


def Normal(mu: float, sigma: float) -> Prior:  # noqa: N802
    """Normal prior with mean ``mu`` and standard deviation ``sigma > 0``.

    Examples
    --------
    >>> Normal(0.0, 2.0).mean()
    0.0
    """
    args = _finite("normal", mu=mu, sigma=sigma)
    if args["sigma"] <= 0:
        raise ValueError(f"normal prior: sigma={sigma!r} must be > 0")
    return _representable(Prior("normal", args))


def LogNormal(mu: float, sigma: float) -> Prior:  # noqa: N802
    """Log-normal prior: ``log(value) ~ Normal(mu, sigma)``.

    Examples
    --------
    >>> round(LogNormal(0.0, 0.1).mean(), 4)
    1.005
    """
    args = _finite("lognormal", mu=mu, sigma=sigma)
    if args["sigma"] <= 0:
        raise ValueError(f"lognormal prior: sigma={sigma!r} must be > 0")
    return _representable(Prior("lognormal", args))


def HalfNormal(sigma: float) -> Prior:  # noqa: N802
    """Half-normal prior on the positive reals with scale ``sigma > 0``.

    Examples
    --------
    >>> HalfNormal(1.0).in_support(-1.0)
    False
    """
    args = _finite("halfnormal", sigma=sigma)
    if args["sigma"] <= 0:
        raise ValueError(f"halfnormal prior: sigma={sigma!r} must be > 0")
    return _representable(Prior("halfnormal", args))


def Custom(factory: Callable[..., Any], *, mean: float = 0.0, scale: float = 1.0) -> Prior:  # noqa: N802
    """Any PyMC distribution as a prior.

    Parameters
    ----------
    factory : callable
        ``factory(name, **kwargs)`` creating the random variable in the current model,
        e.g. ``lambda name, **kw: pm.Gamma(name, alpha=2, beta=0.01, **kw)``.
    mean, scale : float
        A representative value (used as Taylor expansion point / initial check) and
        magnitude (used for finite-difference step sizes).

    Examples
    --------
    >>> import pymc as pm
    >>> p = Custom(lambda name, **kw: pm.Gamma(name, alpha=2.0, beta=0.01, **kw), mean=200.0)
    >>> p.mean()
    200.0
    """
    if not callable(factory):
        raise TypeError("custom prior: factory must be callable as factory(name, **kwargs)")
    return Prior("custom", {}, factory=factory, mean_value=float(mean), typical=float(scale))


_FACTORIES: dict[str, Callable[..., Prior]] = {
    "uniform": Uniform,
    "loguniform": LogUniform,
    "normal": Normal,
    "lognormal": LogNormal,
    "halfnormal": HalfNormal,
}


def as_prior(spec: Prior | dict[str, Any] | Callable[..., Any], *, name: str = "?") -> Prior:
    """Turn a prior specification into a :class:`Prior`.

    Accepts a :class:`Prior`, a dict such as ``{"prior": "uniform", "lower": 50,
    "upper": 300}`` (the TOML form) or a PyMC distribution factory.

    Examples
    --------
    >>> as_prior({"prior": "normal", "mu": 1.0, "sigma": 0.5}, name="k")
    Normal(mu=1, sigma=0.5)
    """
    if isinstance(spec, Prior):
        return spec
    if isinstance(spec, dict):
        spec = dict(spec)
        kind = str(spec.pop("prior", spec.pop("kind", ""))).lower().replace("_", "")
        if kind not in _FACTORIES:
            raise ValueError(
                f"parameter {name!r}: unknown prior {kind!r}; expected one of {sorted(_FACTORIES)}"
            )
        try:
            return _FACTORIES[kind](**spec)
        except (TypeError, ValueError) as err:
            raise type(err)(f"parameter {name!r}: {err}") from err
    if callable(spec):
        return Custom(spec)
    raise TypeError(f"parameter {name!r}: cannot interpret prior {spec!r}")
