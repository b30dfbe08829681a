"""M5: GP δ with a non-stationary covariance (paper Section 3.5, Eq. 14).

``k(x, x') = k_SE(x, x') + w1 exp(-w2 t) · 1[t = t']``: the squared-exponential kernel
of M4 plus a term, added only where the time input of the two points is equal, whose
size decays with time (``w1, w2 > 0``): the discrepancy is more uncertain early on.
With ``w1 = 0`` it is exactly M4's kernel.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import pymc as pm
import pytensor.tensor as pt

from kohpymc.discrepancy.base import ModelContext
from kohpymc.discrepancy.functions import MeanSpec
from kohpymc.discrepancy.gp import GaussianProcess
from kohpymc.priors import HalfNormal, Prior, as_prior

__all__ = ["NonStationaryGP", "DecayingVariance"]


class DecayingVariance(pm.gp.cov.Covariance):
    r"""Time-decaying variance term of Eq. (14).

    .. math::

        k_2(x, x') = w_1 \exp(-w_2 t) \, \mathbb{1}[t = t']

    where ``t`` is the single active column.  Rows sharing a time value are fully
    correlated through this term (as Eq. 14 is written); it is positive semi-definite
    for ``w1 >= 0``.

    Parameters
    ----------
    input_dim : int
        Number of columns of X.
    w1, w2 : tensor-like
        Scale and decay rate.
    active_dims : list of int
        One column: the time input.

    Examples
    --------
    >>> import numpy as np
    >>> k = DecayingVariance(1, w1=2.0, w2=1.0, active_dims=[0])
    >>> np.round(k(np.array([[0.0], [1.0]])).eval(), 3)
    array([[2.   , 0.   ],
           [0.   , 0.736]])
    """

    def __init__(self, input_dim: int, w1: Any, w2: Any, active_dims: Sequence[int]) -> None:
        if len(active_dims) != 1:
            raise ValueError("DecayingVariance acts on exactly one (time) column")
        super().__init__(input_dim, list(active_dims))
        self.w1 = pt.as_tensor_variable(w1)
        self.w2 = pt.as_tensor_variable(w2)

    def diag(self, X):
        """``w1 exp(-w2 t)`` on the diagonal."""
        X, _ = self._slice(X, None)
        return self.w1 * pt.exp(-self.w2 * X[:, 0])

    def full(self, X, Xs=None):
        """The matrix ``w1 exp(-w2 t) 1[t = t']`` between the rows of X and Xs."""
        X, Xs = self._slice(X, Xs)
        t = X[:, 0]
        ts = t if Xs is None else Xs[:, 0]
        same = pt.eq(t[:, None], ts[None, :])
        return pt.switch(same, (self.w1 * pt.exp(-self.w2 * t))[:, None], 0.0)


class NonStationaryGP(GaussianProcess, kind="nonstationary_gp"):
    """M5: GP discrepancy with the non-stationary covariance of Eq. (14).

    Parameters
    ----------
    inputs : sequence of str
        Inputs of the SE kernel and default mean.
    time : str
        The time input ``t`` of the decaying term (need not be in ``inputs``).
    mean, amplitude_prior, lengthscale_prior :
        As for :class:`~kohpymc.discrepancy.gp.GaussianProcess`.
    w1_prior : Prior, optional
        Prior of ``w1`` (``"delta_w1"``); default ``HalfNormal(sd(y)²)``.
    w2_prior : Prior, optional
        Prior of ``w2`` (``"delta_w2"``); default ``HalfNormal(5 / range(t))``.

    Examples
    --------
    >>> NonStationaryGP(["t"], time="t").label
    'M5'
    """

    label = "M5"
    description = "non-stationary GP"
    study_defaults = {"inputs": "inputs", "time": "time"}

    def __init__(
        self,
        inputs: Sequence[str],
        time: str,
        mean: MeanSpec | Sequence[str] | None = None,
        *,
        amplitude_prior: Prior | dict[str, Any] | None = None,
        lengthscale_prior: Prior | dict[str, Any] | None = None,
        w1_prior: Prior | dict[str, Any] | None = None,
        w2_prior: Prior | dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            inputs, mean, amplitude_prior=amplitude_prior, lengthscale_prior=lengthscale_prior
        )
        self.time = str(time)
        self.w1_prior = None if w1_prior is None else as_prior(w1_prior, name="delta_w1")
        self.w2_prior = None if w2_prior is None else as_prior(w2_prior, name="delta_w2")

    @property
    def inputs(self) -> tuple[str, ...]:
        """Kernel, mean and time inputs."""
        return tuple(dict.fromkeys(super().inputs + (self.time,)))

    def kernel(self, ctx: ModelContext, active_dims: list[int]):
        """``η² ExpQuad + DecayingVariance(w1, w2)`` over the time column."""
        w1 = (self.w1_prior or HalfNormal(ctx.y_scale**2)).create("delta_w1")
        w2 = (self.w2_prior or HalfNormal(5.0 / ctx.span[self.time])).create("delta_w2")
        decaying = DecayingVariance(
            len(ctx.input_names), w1, w2, active_dims=[ctx.column(self.time)]
        )
        return self.stationary_kernel(ctx, active_dims) + decaying
