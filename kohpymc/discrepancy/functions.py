"""Parametric functions of the inputs used as discrepancy means and log-variances.

* :class:`LinearBasis` — ``c_0 + Σ_k c_k z_k`` with ``z_k = (x_k - centre_k) / scale_k``
  the calibration-standardised inputs (so coefficients are in output units per
  standard deviation of the input, and their priors can share one scale).
* :class:`ParametricFunction` — any user function ``f(inputs, params)`` written with
  ``pytensor.tensor`` operations on the raw inputs, e.g. ``φ4 exp(φ5 t)`` of Eq. (29).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pymc as pm
import pytensor.tensor as pt

from kohpymc.discrepancy.base import ModelContext
from kohpymc.priors import Prior, as_prior

__all__ = ["LinearBasis", "ParametricFunction", "MeanSpec", "as_function", "marginalizable"]

BuiltFunction = Callable[[pt.TensorVariable], pt.TensorVariable]


class LinearBasis:
    """Linear function of standardised inputs: ``c_0 + Σ_k c_k z_k``.

    Parameters
    ----------
    inputs : sequence of str
        Terms of the basis besides the intercept: input names, or products of input
        names such as ``"x*P"`` (the product of the standardised inputs, for an
        interaction).  May be empty for an intercept-only function.
    intercept : bool
        Include ``c_0``.
    prior : Prior, optional
        Prior of every coefficient; default ``Normal(offset, 2 · y_scale)`` sized from
        the calibration output (``offset`` is 0 for a mean, see ``offset``).
    offset : float or None
        Centre of the default intercept prior; ``None`` means "a log-variance": the
        intercept prior is then ``Normal(log((0.1 y_scale)²), 2.5)`` and slopes
        ``Normal(0, 1)``.
    scalar : bool
        For an intercept-only basis, store the coefficient as a scalar (no dim).

    Examples
    --------
    >>> LinearBasis(["x"]).terms
    ('1', 'x')
    >>> LinearBasis(["x", "P", "x*P"]).inputs
    ('x', 'P')
    """

    def __init__(
        self,
        inputs: Sequence[str] = (),
        *,
        intercept: bool = True,
        prior: Prior | dict[str, Any] | None = None,
        offset: float | None = 0.0,
        scalar: bool = False,
    ) -> None:
        if isinstance(inputs, str):
            inputs = [inputs]
        #: basis terms other than the intercept: input names or products such as "x*P"
        self.products: tuple[str, ...] = tuple(str(t).replace(" ", "") for t in inputs)
        factors = [f for t in self.products for f in t.split("*")]
        if any(not f for f in factors):
            raise ValueError(f"LinearBasis: empty factor in terms {list(self.products)}")
        self.inputs: tuple[str, ...] = tuple(dict.fromkeys(factors))
        self.intercept = bool(intercept)
        if not self.inputs and not self.intercept:
            raise ValueError("LinearBasis needs an intercept or at least one input")
        self.prior = None if prior is None else as_prior(prior, name="linear basis")
        self.offset = offset
        self.scalar = bool(scalar) and not self.inputs and self.intercept

    @property
    def terms(self) -> tuple[str, ...]:
        """Names of the basis terms (``"1"`` is the intercept)."""
        return (("1",) if self.intercept else ()) + self.products

    def design(self, ctx: ModelContext, X: pt.TensorVariable) -> pt.TensorVariable:
        """The ``(m, k)`` basis matrix at inputs ``X`` (columns as :attr:`terms`)."""
        cols = []
        for term in self.products:
            col = None
            for factor in term.split("*"):
                z = ctx.standardized(X, factor)
                col = z if col is None else col * z
            cols.append(col)
        if self.intercept:
            cols = [pt.ones_like(X[:, 0])] + cols
        return pt.stack(cols, axis=1)

    def gaussian_prior(self, ctx: ModelContext) -> tuple[np.ndarray, np.ndarray] | None:
        """Prior means and sds of the coefficients if they are independent normals."""
        k = len(self.terms)
        if self.prior is not None:
            if self.prior.kind != "normal":
                return None
            return np.full(k, self.prior.args["mu"]), np.full(k, self.prior.args["sigma"])
        mu = np.zeros(k)
        if self.offset is None:  # log-variance: log((0.1 y_scale)^2) +- 2.5, slopes N(0, 1)
            sd = np.ones(k)
            if self.intercept:
                mu[0] = 2.0 * np.log(0.1 * ctx.y_scale)
                sd[0] = 2.5
            return mu, sd
        if self.intercept:
            mu[0] = self.offset
        return mu, np.full(k, 2.0 * ctx.y_scale)

    def _add_coord(self, name: str) -> str | None:
        if self.scalar:
            return None
        dim = f"{name}_term"
        pm.modelcontext(None).add_coord(dim, list(self.terms))
        return dim

    def _shape(self) -> dict[str, Any]:
        return {"shape": (1,)} if self.scalar else {}

    def _stored(self, name: str, coef: pt.TensorVariable, dim: str | None):
        """Expose the coefficients under ``name`` (a scalar for ``scalar=True``)."""
        if self.scalar:
            return pm.Deterministic(name, coef[0])
        return pm.Deterministic(name, coef, dims=dim)

    def build(self, ctx: ModelContext, name: str) -> BuiltFunction:
        """Create the coefficient vector ``name`` (dim ``f"{name}_term"``); return f(X)."""
        for inp in self.inputs:
            ctx.column(inp)  # clear error if the input is missing
        dim = self._add_coord(name)
        moments = self.gaussian_prior(ctx)
        if self.scalar:
            if moments is None:
                coef = self.prior.create(name)  # type: ignore[union-attr]
            else:
                coef = pm.Normal(name, mu=moments[0][0], sigma=moments[1][0])
            coef = pt.stack([coef])
        elif moments is None:
            coef = self.prior.create(name, dims=dim)  # type: ignore[union-attr]
        else:
            coef = pm.Normal(name, mu=moments[0], sigma=moments[1], dims=dim)
        return lambda X: pt.dot(self.design(ctx, X), coef)

    def build_marginalized(
        self,
        ctx: ModelContext,
        name: str,
        B: pt.TensorVariable,
        cov_inv_B: pt.TensorVariable,
        cov_inv_resid: pt.TensorVariable,
    ) -> BuiltFunction:
        """Coefficients integrated out of the likelihood and recovered by whitening.

        With Gaussian coefficients ``c ~ N(m0, S0)`` and ``y | c ~ N(G + B c, C0)``,
        ``c | y, θ ~ N(m, P⁻¹)`` where ``P = S0⁻¹ + Bᵀ C0⁻¹ B`` and
        ``m = P⁻¹ (S0⁻¹ m0 + Bᵀ C0⁻¹ (y - G))``.  The sampler sees a standard normal
        ``f"{name}_white"`` = z and ``c = m + L_P⁻ᵀ z`` (``P = L_P L_Pᵀ``) is stored as the
        deterministic ``name``: the joint density of (θ, z) is ``p(θ | y) N(z; 0, I)``,
        so the E–coefficient ridge disappears from the sampled space.

        ``cov_inv_B`` is ``C0⁻¹ B`` and ``cov_inv_resid`` is ``C0⁻¹ (y - G)``.
        """
        dim = self._add_coord(name)
        m0, s0 = self.gaussian_prior(ctx)  # type: ignore[misc]
        precision = pt.diag(1.0 / s0**2) + pt.dot(B.T, cov_inv_B)
        chol = pt.linalg.cholesky(precision)
        rhs = m0 / s0**2 + pt.dot(B.T, cov_inv_resid)
        mean = pt.linalg.cho_solve((chol, True), rhs)
        white = pm.Normal(f"{name}_white", 0.0, 1.0, dims=dim, **self._shape())
        coef = mean + pt.linalg.solve_triangular(chol.T, white, lower=False)
        coef = self._stored(name, coef, dim)
        if self.scalar:
            coef = pt.stack([coef])
        return lambda X: pt.dot(self.design(ctx, X), coef)

    def __repr__(self) -> str:
        return f"LinearBasis({list(self.products)}, intercept={self.intercept})"


class ParametricFunction:
    """A user-written function of raw inputs and named parameters.

    Parameters
    ----------
    function : callable
        ``function(inputs, params) -> tensor`` using ``pytensor.tensor`` operations;
        ``inputs`` maps names to 1-D tensors, ``params`` names to scalar tensors.
    parameters : mapping
        Parameter name -> prior (as for :class:`~kohpymc.physics.PhysicsModel`).
    inputs : sequence of str
        Inputs the function reads.

    Examples
    --------
    >>> import pytensor.tensor as pt
    >>> from kohpymc import Normal
    >>> f = ParametricFunction(lambda v, p: p["a"] * pt.exp(p["b"] * v["t"]),
    ...                        {"a": Normal(0, 1), "b": Normal(0, 1)}, inputs=["t"])
    >>> f.inputs
    ('t',)
    """

    def __init__(
        self,
        function: Callable[..., Any],
        parameters: Mapping[str, Prior | dict[str, Any] | Callable[..., Any]],
        *,
        inputs: Sequence[str],
    ) -> None:
        if not callable(function):
            raise TypeError("ParametricFunction: function must be callable(inputs, params)")
        self.function = function
        self.parameters = {str(k): as_prior(v, name=str(k)) for k, v in parameters.items()}
        self.inputs = tuple([inputs] if isinstance(inputs, str) else inputs)

    def build(self, ctx: ModelContext, name: str) -> BuiltFunction:
        """Create parameters ``f"{name}_{param}"``; return f(X)."""
        params = {k: p.create(f"{name}_{k}") for k, p in self.parameters.items()}
        cols = {inp: ctx.column(inp) for inp in self.inputs}

        def evaluate(X: pt.TensorVariable) -> pt.TensorVariable:
            values = {inp: X[:, j] for inp, j in cols.items()}
            out = pt.as_tensor_variable(self.function(values, params))
            return out + pt.zeros_like(X[:, 0])

        return evaluate

    def __repr__(self) -> str:
        return f"ParametricFunction(inputs={list(self.inputs)}, parameters={self.parameters})"


MeanSpec = LinearBasis | ParametricFunction


def marginalizable(spec: Any, ctx: ModelContext) -> bool:
    """Whether ``spec`` is linear with independent-normal coefficients (integrable)."""
    return (
        ctx.marginalize and isinstance(spec, LinearBasis) and spec.gaussian_prior(ctx) is not None
    )


def as_function(spec: Any, *, offset: float | None = 0.0) -> MeanSpec:
    """Turn ``None``/list of input names/a function spec into a function spec.

    Examples
    --------
    >>> as_function(["x"]).terms
    ('1', 'x')
    """
    if isinstance(spec, LinearBasis | ParametricFunction):
        return spec
    if spec is None:
        return LinearBasis((), intercept=True, offset=offset)
    if isinstance(spec, str):
        spec = [spec]
    if isinstance(spec, Sequence):
        return LinearBasis(tuple(spec), offset=offset)
    raise TypeError(f"cannot use {spec!r} as a mean/variance function")
