"""The shared interface of discrepancy formulations and the build context they use.

A formulation is a small, reusable *specification* (priors, basis, kernel choice).
Inside a PyMC model context, :meth:`Discrepancy.build` receives a :class:`ModelContext`
(calibration inputs, the physics output ``G`` as a tensor, the noise sd, scales), adds
its parameters and the observed likelihood of ``y_D = G + δ + ε`` named ``"y"``, and
returns a :data:`Predictor`: a function that, given new inputs and the physics output
there, returns ``y_m = G + δ`` at those inputs (adding any random variables needed, e.g.
the GP conditional).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pytensor.tensor as pt

__all__ = ["Discrepancy", "ModelContext", "Predictor"]

#: ``predictor(X_new, G_new) -> y_m`` at new inputs; ``X_new`` has the columns of
#: :attr:`ModelContext.input_names`.
Predictor = Callable[[pt.TensorVariable, pt.TensorVariable], pt.TensorVariable]


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
        Measurement-noise sd σ_obs (a constant when known, else a random variable).
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


class Discrepancy(ABC):
    """Base class of the discrepancy formulations (paper Section 3).

    Subclasses set :attr:`label` (``"M0"`` ... ``"M5"``) and :attr:`description` and
    implement :meth:`build`.  A new formulation needs only its likelihood and its
    prediction rule.

    Examples
    --------
    >>> from kohpymc.discrepancy import ConstantBias
    >>> ConstantBias().label
    'M1'
    """

    label: ClassVar[str] = ""
    description: ClassVar[str] = ""
    #: True when δ is independent across rows given its parameters (pointwise likelihood)
    independent_rows: ClassVar[bool] = False
    #: NUTS target acceptance used when the caller gives none
    default_target_accept: ClassVar[float] = 0.9

    @property
    def inputs(self) -> tuple[str, ...]:
        """Inputs the discrepancy depends on (beyond the physics inputs)."""
        return ()

    @abstractmethod
    def build(self, ctx: ModelContext) -> Predictor:
        """Add parameters and the observed likelihood ``"y"``; return a predictor."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
