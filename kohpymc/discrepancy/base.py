"""The shared interface of discrepancy formulations, their build record and registry.

A formulation is a small, reusable *specification* (priors, basis, kernel choice).
Inside a PyMC model context, :meth:`Discrepancy.build` receives a :class:`ModelContext`
(calibration inputs, the physics output ``G`` as a tensor, the noise sd, scales), adds
its parameters and the observed variable ``"y"`` of ``y_D = G + δ + ε``, and returns a
:class:`Likelihood`: one record saying what it built — the predictor of ``G + δ`` at new
inputs, the mean of ``y`` given the model's variables and, for Gaussian formulations,
its covariance (or variances when rows are independent).  Identifiability checks, LOO,
prediction and studies read this record; nothing downstream inspects graph positions.

Every concrete formulation registers under a ``kind`` string (``class X(Discrepancy,
kind="gp")``), which gives TOML parsing (:func:`from_dict`), :meth:`Discrepancy.to_dict`
and the contract tests with no list to edit.
"""

from __future__ import annotations

import functools
import inspect
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pytensor.tensor as pt

__all__ = [
    "Discrepancy",
    "FormulationSpecError",
    "Likelihood",
    "ModelContext",
    "Predictor",
    "formulation_kinds",
    "formulation_class",
    "from_dict",
]

#: ``predictor(X_new, G_new) -> y_m`` at new inputs; ``X_new`` has the columns of
#: :attr:`ModelContext.input_names`.
Predictor = Callable[[pt.TensorVariable, pt.TensorVariable], pt.TensorVariable]

#: ``loo(posterior, built) -> xarray.Dataset`` of pointwise log densities of ``"y"``
PointwiseLogLikelihood = Callable[..., Any]


@dataclass
class ModelContext:
    """What a formulation needs to build its part of the calibration model.

    Attributes
    ----------
    input_names : tuple of str
        Columns of ``X`` (the physics inputs plus any extra discrepancy inputs).
    X : numpy.ndarray
        ``(n, d)`` calibration inputs.
    y : numpy.ndarray
        ``(n,)`` observed outputs.
    G : TensorVariable
        Physics output at the calibration rows.
    physics_mean : callable
        ``physics_mean(X) -> G(X; θ)`` for any ``(m, d)`` input tensor.
    noise_sd : TensorVariable
        The sd of the independent error each row's likelihood adds: σ_obs (a constant
        when known, else a random variable) or, when the physics model has a variance
        (an emulator), ``sqrt(σ_obs² + v(x_i; θ))`` per row.
    y_scale : float
        A positive output scale (sd of ``y``) used to size default priors.
    center, scale : dict
        Per-input centre and scale of the calibration inputs (used to standardise).
    span : dict
        Per-input range (max - min) of the calibration inputs (1 when constant).
    obs_dim : str
        Name of the data-row dimension.
    marginalize : bool
        Integrate linear discrepancy-mean coefficients with normal priors out of the
        likelihood (recovering them by whitening); ``False`` samples them directly.
    measurement_sd : TensorVariable, optional
        σ_obs alone (a scalar), when ``noise_sd`` also holds a physics variance;
        ``None`` means ``noise_sd`` is σ_obs.
    physics_covariance : TensorVariable, optional
        ``(n, n)`` covariance of the physics output between the calibration rows (an
        emulator's ``Σ_η(θ)``), given only to formulations whose
        :attr:`Discrepancy.accepts_physics_covariance` is true: they add it to the
        likelihood covariance, ``N(G + μ_δ, Σ_η + Σ_δ + σ_obs² I)``.  It may be a
        :func:`~kohpymc.gaussian.low_rank_covariance` (a principal-component
        emulator's): :func:`~kohpymc.gaussian.add_to_covariance` keeps that structure
        for the Woodbury likelihood.
    """

    input_names: tuple[str, ...]
    X: np.ndarray
    y: np.ndarray
    G: pt.TensorVariable
    physics_mean: Callable[[pt.TensorVariable], pt.TensorVariable]
    noise_sd: pt.TensorVariable
    y_scale: float
    center: dict[str, float]
    scale: dict[str, float]
    span: dict[str, float]
    obs_dim: str = "obs"
    marginalize: bool = True
    extra: dict[str, object] = field(default_factory=dict)
    measurement_sd: pt.TensorVariable | None = None
    physics_covariance: pt.TensorVariable | None = None

    @property
    def sigma_obs(self) -> pt.TensorVariable:
        """The measurement-noise sd σ_obs alone (a scalar)."""
        return self.noise_sd if self.measurement_sd is None else self.measurement_sd

    def column(self, name: str) -> int:
        """Index of input ``name`` in ``X``."""
        try:
            return self.input_names.index(name)
        except ValueError:
            raise KeyError(
                f"discrepancy input {name!r} is not in the data; available {list(self.input_names)}"
            ) from None

    def standardized(self, X: pt.TensorVariable, name: str) -> pt.TensorVariable:
        """``(x - centre) / scale`` of input ``name`` from an input tensor."""
        return (X[:, self.column(name)] - self.center[name]) / self.scale[name]


@dataclass(frozen=True)
class Likelihood:
    """What a formulation built: the record every later step reads.

    Attributes
    ----------
    predictor : Predictor
        ``predictor(X_new, G_new)`` returns ``y_m = G + δ`` at new inputs (adding any
        random variables needed, e.g. a GP conditional, with dim ``"pred"``).
    mean : TensorVariable
        ``E[y | model variables]`` at the calibration rows (length ``n``): ``G + μ_δ``
        for M1–M3, ``G + m`` for the GPs.  The Taylor identifiability check
        differentiates it.
    covariance : TensorVariable, optional
        ``Cov[y | model variables]`` (``n × n``) of a Gaussian likelihood; exact
        leave-one-out and the Fisher check use it.
    variance : TensorVariable, optional
        Per-row variances when ``y`` is Gaussian with independent rows (instead of
        ``covariance``).
    independent_rows : bool
        Rows of ``y`` are independent given the model variables, so PyMC's own
        elementwise log-likelihood is the pointwise one (LOO, WAIC).
    pointwise : callable, optional
        ``pointwise(posterior, built) -> Dataset`` computing pointwise log densities of
        ``"y"`` (overrides the exact Gaussian leave-one-out, e.g. for structured
        covariances).
    observed : str
        Name of the observed variable.

    Examples
    --------
    >>> import pytensor.tensor as pt
    >>> record = Likelihood(predictor=lambda X, G: G, mean=pt.zeros(3), variance=pt.ones(3),
    ...                     independent_rows=True)
    >>> record.gaussian
    True
    """

    predictor: Predictor
    mean: pt.TensorVariable
    covariance: pt.TensorVariable | None = None
    variance: pt.TensorVariable | None = None
    independent_rows: bool = False
    pointwise: PointwiseLogLikelihood | None = None
    observed: str = "y"

    @property
    def gaussian(self) -> bool:
        """Whether the record gives a Gaussian likelihood (a covariance or variances)."""
        return self.covariance is not None or self.variance is not None


class FormulationSpecError(ValueError):
    """A formulation specification (TOML table or dict) that cannot be used.

    ``key`` names the entry at fault (``"type"``, an option), when there is one.
    """

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key


_REGISTRY: dict[str, type[Discrepancy]] = {}


def _record_init_arguments(init: Callable[..., None]) -> Callable[..., None]:
    """Wrap ``__init__`` so an instance remembers the arguments it was built with."""
    signature = inspect.signature(init)

    @functools.wraps(init)
    def wrapped(self: Any, *args: Any, **kwargs: Any) -> None:
        if "_init_arguments" not in self.__dict__:  # the outermost __init__ only
            bound = signature.bind(self, *args, **kwargs)
            arguments = dict(bound.arguments)
            arguments.pop(next(iter(signature.parameters)))  # self
            for name, param in signature.parameters.items():
                if param.kind is inspect.Parameter.VAR_KEYWORD and name in arguments:
                    arguments.update(arguments.pop(name))
            self.__dict__["_init_arguments"] = arguments
        init(self, *args, **kwargs)

    return wrapped


def _plain(value: Any, where: str) -> Any:
    """A TOML-friendly form of a constructor argument (priors as tables)."""
    from kohpymc.priors import Prior

    if isinstance(value, Prior):
        if value.kind == "custom":
            raise TypeError(f"{where}: a custom (callable) prior has no plain form")
        return {"prior": value.kind, **value.args}
    if isinstance(value, str | int | float | bool) or value is None:
        return value
    if isinstance(value, list | tuple):
        return [_plain(v, where) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain(v, f"{where}.{k}") for k, v in value.items()}
    raise TypeError(f"{where}: {type(value).__name__} has no plain (TOML) form")


class Discrepancy(ABC):
    """Base class of the discrepancy formulations (paper Section 3).

    Subclasses set :attr:`label` (``"M0"`` ... ``"M6"``), :attr:`description` and,
    to be found by configuration files, a ``kind`` given at class creation
    (``class MyBias(Discrepancy, kind="my_bias")``); they implement :meth:`build`.

    Examples
    --------
    >>> from kohpymc.discrepancy import ConstantBias
    >>> ConstantBias().label, ConstantBias.kind
    ('M1', 'constant')
    >>> ConstantBias(prior={"prior": "normal", "mu": 0, "sigma": 2}).to_dict()
    {'type': 'constant', 'prior': {'prior': 'normal', 'mu': 0, 'sigma': 2}}
    """

    kind: ClassVar[str] = ""
    label: ClassVar[str] = ""
    description: ClassVar[str] = ""
    #: NUTS target acceptance used when the caller gives none
    default_target_accept: ClassVar[float] = 0.9
    #: constructor argument -> study setting filling it when a study file omits it
    #: (``"inputs"``: the physics inputs, ``"time"``: the physics time input)
    study_defaults: ClassVar[Mapping[str, str]] = {}
    #: constructor arguments that only Python code can give (callables)
    code_only: ClassVar[tuple[str, ...]] = ()
    #: :meth:`build` adds :attr:`ModelContext.physics_covariance` (an emulator's
    #: correlated error) to its likelihood covariance; otherwise only the emulator's
    #: per-row variance reaches it, through ``noise_sd``
    accepts_physics_covariance: ClassVar[bool] = False

    def __init_subclass__(cls, kind: str | None = None, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "__init__" in cls.__dict__:
            cls.__init__ = _record_init_arguments(cls.__dict__["__init__"])  # type: ignore[method-assign]
        if kind is not None:
            if kind in _REGISTRY and _REGISTRY[kind].__qualname__ != cls.__qualname__:
                raise ValueError(
                    f"formulation kind {kind!r} is taken by {_REGISTRY[kind].__name__}"
                )
            cls.kind = kind
            _REGISTRY[kind] = cls

    @property
    def inputs(self) -> tuple[str, ...]:
        """Inputs the discrepancy depends on (beyond the physics inputs)."""
        return ()

    def noise_partner(self) -> tuple[str, str] | None:
        """The parameter whose variance adds to σ_obs² in the likelihood, or None.

        ``(name, "sd")`` for a scalar sd σ_δ (only σ_obs² + σ_δ² is identified when the
        noise is unknown), ``(name, "log_variance")`` for coefficients whose first entry
        is the log-variance at the centre of the inputs.  The sampler then uses
        total-sd / log-ratio coordinates for the pair
        (:class:`kohpymc.reparameterization.VarianceShare`).

        Examples
        --------
        >>> from kohpymc.discrepancy import IIDGaussian, NoDiscrepancy
        >>> IIDGaussian().noise_partner(), NoDiscrepancy().noise_partner()
        (('delta_sd', 'sd'), None)
        """
        return None

    def scale_parameters(self) -> tuple[str, ...]:
        """Parameters that set how much of the data's shape the discrepancy takes up.

        Where they are large the physics parameters are held less and move (a funnel);
        with ``reparameterize`` the sampler follows the others' conditional modes and
        scales along the strongest of them
        (:func:`kohpymc.scale_funnel.scale_funnel_plan`).  None by default.

        Examples
        --------
        >>> from kohpymc.discrepancy import InputDependentGaussian, NoDiscrepancy
        >>> InputDependentGaussian(["x"]).scale_parameters(), NoDiscrepancy().scale_parameters()
        (('delta_logvar',), ())
        """
        return ()

    @abstractmethod
    def build(self, ctx: ModelContext) -> Likelihood:
        """Add parameters and the observed variable ``"y"``; return the record."""

    def to_dict(self) -> dict[str, Any]:
        """The formulation as a plain table (the TOML form): ``type`` plus its options.

        Only the arguments given to the constructor appear; :func:`from_dict` rebuilds
        an equal formulation.  Raises ``TypeError`` for options only code can give.
        """
        if not self.kind:
            raise TypeError(f"{type(self).__name__} is not registered under a kind")
        args = self.__dict__.get("_init_arguments", {})
        where = f"{self.kind} formulation"
        return {"type": self.kind, **{k: _plain(v, f"{where}.{k}") for k, v in args.items()}}

    def __repr__(self) -> str:
        args = self.__dict__.get("_init_arguments", {})
        inner = ", ".join(f"{k}={v!r}" for k, v in args.items())
        return f"{type(self).__name__}({inner})"


def formulation_kinds() -> dict[str, type[Discrepancy]]:
    """Registered formulation kinds (``type`` strings of study files) and their classes.

    Examples
    --------
    >>> import kohpymc
    >>> sorted(formulation_kinds())[:3]
    ['constant', 'gp', 'grid_gp']
    """
    return dict(_REGISTRY)


def formulation_class(kind: str) -> type[Discrepancy]:
    """The class registered under ``kind``.

    Examples
    --------
    >>> import kohpymc
    >>> formulation_class("iid").label
    'M2'
    """
    try:
        return _REGISTRY[kind]
    except KeyError:
        raise FormulationSpecError(
            f"unknown formulation type {kind!r}; known: {sorted(_REGISTRY)}", key="type"
        ) from None


def _options(cls: type[Discrepancy]) -> dict[str, inspect.Parameter]:
    params = inspect.signature(cls.__init__).parameters
    return {
        k: p
        for k, p in list(params.items())[1:]
        if p.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
        and k not in cls.code_only
    }


def from_dict(spec: str | Mapping[str, Any], **study: Any) -> Discrepancy:
    """Build a formulation from its plain form (a ``type`` string or a table).

    Parameters
    ----------
    spec : str or mapping
        ``"iid"`` or ``{"type": "gp", "inputs": ["x"]}``; other keys are constructor
        options (priors as tables such as ``{"prior": "halfnormal", "sigma": 1}``).
    **study :
        Study settings filling options the table leaves out, as the class's
        :attr:`~Discrepancy.study_defaults` say (``inputs=[...]``, ``time="t"``).

    Raises
    ------
    FormulationSpecError
        Naming the option at fault (``"gp.inputs"``), the unknown type or key.

    Examples
    --------
    >>> import kohpymc
    >>> from_dict({"type": "gp"}, inputs=["x"]).inputs
    ('x',)
    >>> from_dict({"type": "gp", "lenghtscale": 1})
    Traceback (most recent call last):
    ...
    kohpymc.discrepancy.base.FormulationSpecError: gp: unknown option(s) ['lenghtscale']; ...
    """
    if isinstance(spec, str):
        spec = {"type": spec}
    if not isinstance(spec, Mapping) or "type" not in spec:
        raise FormulationSpecError(
            "a formulation must be a type name or a table with 'type'", key="type"
        )
    kind = spec["type"]
    cls = formulation_class(str(kind))
    allowed = _options(cls)
    opts = {str(k): v for k, v in spec.items() if k != "type"}
    unknown = sorted(set(opts) - set(allowed))
    if unknown:
        raise FormulationSpecError(
            f"{kind}: unknown option(s) {unknown}; allowed: {sorted(allowed)}"
        )
    for arg, setting in cls.study_defaults.items():
        if arg not in opts and study.get(setting) is not None:
            opts[arg] = study[setting]
    missing = [
        k for k, p in allowed.items() if p.default is inspect.Parameter.empty and k not in opts
    ]
    if missing:
        raise FormulationSpecError(f"{kind}: required option(s) {missing} missing")
    try:
        return cls(**opts)
    except (TypeError, ValueError, KeyError) as err:
        raise FormulationSpecError(f"{kind}: {type(err).__name__}: {err}") from err
