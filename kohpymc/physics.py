"""Physics models y = G(x; θ) and their wrapping as PyTensor Ops with gradients.

A user hands over a plain numpy function ``model(inputs, params) -> ndarray`` where
``inputs`` maps input names to 1-D arrays (one entry per data row) and ``params`` maps
parameter names to floats.  :class:`PhysicsModel` wraps it as a PyTensor ``Op`` whose
gradient is the vector-Jacobian product ``g @ J``; ``J = ∂G/∂θ`` comes from a
user-supplied Jacobian when given, otherwise from finite differences:

* ``fd_scheme="central"`` (default): ``J[:, j] = (G(θ + h_j e_j) - G(θ - h_j e_j)) / 2h_j``
  with ``h_j = ε^{1/3} · max(|θ_j|, s_j)``, ``ε`` the float64 machine epsilon
  (ε^{1/3} ≈ 6.1e-6) and ``s_j`` the prior's typical magnitude.  Truncation error is
  O(h²); cost is ``2p`` model evaluations per gradient.
* ``fd_scheme="forward"``: ``(G(θ + h_j e_j) - G(θ)) / h_j`` with ``h_j = √ε · max(|θ_j|, s_j)``
  (√ε ≈ 1.5e-8); O(h) error, ``p + 1`` evaluations per gradient.

Using ``max(|θ_j|, s_j)`` keeps the step from collapsing when a parameter passes
through zero.  NUTS needs one gradient per leapfrog step, so a gradient costs
``2p`` (or ``p + 1``) times one model run: supply ``jacobian=`` when you can.

A model written with ``pytensor.tensor`` operations (``backend="pytensor"``) is put
into the graph directly and gets exact automatic differentiation.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import numpy as np
import pytensor.tensor as pt
from pytensor.gradient import disconnected_type
from pytensor.graph.basic import Apply
from pytensor.graph.op import Op

from kohpymc.priors import Prior, as_prior

__all__ = ["PhysicsModel", "PhysicsModelError"]

_EPS = np.finfo(np.float64).eps


class PhysicsModelError(RuntimeError):
    """The physics function failed (raised, returned non-finite values or a wrong shape)."""


def _format_params(params: Mapping[str, float]) -> str:
    return "{" + ", ".join(f"{k}={float(v):.6g}" for k, v in params.items()) + "}"


class PhysicsModel:
    """A physics model ``y = G(x; θ)`` with named inputs and parameters with priors.

    Parameters
    ----------
    function : callable
        ``function(inputs, params) -> array``.  ``inputs`` maps each name in ``inputs``
        to a 1-D array (one entry per data row), ``params`` maps parameter names to
        floats (numpy backend) or scalar tensors (pytensor backend).  Must return one
        value per row.
    parameters : mapping
        Parameter name -> prior: a :class:`~kohpymc.priors.Prior`, a dict such as
        ``{"prior": "uniform", "lower": 50, "upper": 300}``, or a PyMC distribution
        factory ``f(name, **kwargs)``.  The order is the order of θ.
    inputs : sequence of str
        Names of the model inputs x.
    jacobian : callable, optional
        ``jacobian(inputs, params)`` returning ``∂G/∂θ`` as an ``(n, p)`` array with
        columns in parameter order, or a dict parameter name -> ``(n,)`` array.  Without
        it the gradient uses finite differences (see module docstring).
    backend : {"numpy", "pytensor"}
        ``"pytensor"`` when ``function`` is written with ``pytensor.tensor`` operations;
        it then gets exact autodiff.
    fd_scheme : {"central", "forward"}
        Finite-difference scheme for numpy models without a Jacobian.
    fd_relative_step : float, optional
        Override the relative step (defaults ε^{1/3} central, √ε forward).
    on_nonfinite : {"raise", "reject"}
        What to do when the model returns NaN/inf during sampling: raise a
        :class:`PhysicsModelError` naming the parameter values, or reject the point
        (its likelihood becomes zero).  The pre-sampling check always raises.
    name : str, optional
        A label used in messages; defaults to the function name.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import PhysicsModel, Uniform
    >>> def decay(inputs, params):
    ...     return params["a"] * np.exp(-params["k"] * inputs["t"])
    >>> physics = PhysicsModel(decay, {"a": Uniform(0, 5), "k": Uniform(0, 2)}, inputs=["t"])
    >>> physics.evaluate({"t": np.array([0.0, 1.0])}, {"a": 2.0, "k": 0.0})
    array([2., 2.])
    """

    def __init__(
        self,
        function: Callable[..., Any],
        parameters: Mapping[str, Prior | dict[str, Any] | Callable[..., Any]],
        inputs: Sequence[str],
        *,
        jacobian: Callable[..., Any] | None = None,
        backend: Literal["numpy", "pytensor"] = "numpy",
        fd_scheme: Literal["central", "forward"] = "central",
        fd_relative_step: float | None = None,
        on_nonfinite: Literal["raise", "reject"] = "raise",
        name: str | None = None,
    ) -> None:
        if not callable(function):
            raise TypeError("physics function must be callable as function(inputs, params)")
        if isinstance(inputs, str):
            inputs = [inputs]
        self.inputs: tuple[str, ...] = tuple(str(i) for i in inputs)
        if not self.inputs:
            raise ValueError("physics model needs at least one input name")
        if len(set(self.inputs)) != len(self.inputs):
            raise ValueError(f"physics model: duplicate input names in {list(self.inputs)}")
        if not parameters:
            raise ValueError("physics model needs at least one parameter")
        self.parameters: dict[str, Prior] = {
            str(k): as_prior(v, name=str(k)) for k, v in parameters.items()
        }
        clash = set(self.parameters) & set(self.inputs)
        if clash:
            raise ValueError(f"names used both as input and parameter: {sorted(clash)}")
        if backend not in ("numpy", "pytensor"):
            raise ValueError(f"backend must be 'numpy' or 'pytensor', got {backend!r}")
        if fd_scheme not in ("central", "forward"):
            raise ValueError(f"fd_scheme must be 'central' or 'forward', got {fd_scheme!r}")
        if on_nonfinite not in ("raise", "reject"):
            raise ValueError(f"on_nonfinite must be 'raise' or 'reject', got {on_nonfinite!r}")
        if backend == "pytensor" and jacobian is not None:
            raise ValueError("a pytensor model gets exact autodiff; do not pass jacobian=")
        self.function = function
        self.jacobian = jacobian
        self.backend = backend
        self.fd_scheme = fd_scheme
        if fd_relative_step is None:
            fd_relative_step = _EPS ** (1 / 3) if fd_scheme == "central" else np.sqrt(_EPS)
        if not fd_relative_step > 0:
            raise ValueError("fd_relative_step must be > 0")
        self.fd_relative_step = float(fd_relative_step)
        self.on_nonfinite = on_nonfinite
        self.name = name or getattr(function, "__name__", "physics")
        self.n_calls = 0

    # ------------------------------------------------------------------ numpy side
    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of θ in order."""
        return tuple(self.parameters)

    def prior_mean(self) -> dict[str, float]:
        """Prior mean of every parameter (the default expansion/check point)."""
        return {k: p.mean() for k, p in self.parameters.items()}

    def _as_inputs(self, inputs: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], int]:
        missing = [k for k in self.inputs if k not in inputs]
        if missing:
            raise KeyError(
                f"physics model {self.name!r} needs inputs {list(self.inputs)}; "
                f"missing {missing} (got {sorted(inputs)})"
            )
        arrays = {k: np.asarray(inputs[k], dtype=float).reshape(-1) for k in self.inputs}
        sizes = {k: a.size for k, a in arrays.items()}
        if len(set(sizes.values())) != 1:
            raise ValueError(f"physics model {self.name!r}: inputs of unequal length {sizes}")
        return arrays, next(iter(sizes.values()))

    def _as_params(self, params: Mapping[str, float] | Sequence[float]) -> dict[str, float]:
        if isinstance(params, Mapping):
            missing = [k for k in self.parameters if k not in params]
            if missing:
                raise KeyError(f"physics model {self.name!r}: missing parameters {missing}")
            return {k: float(params[k]) for k in self.parameters}
        values = np.asarray(params, dtype=float).reshape(-1)
        if values.size != len(self.parameters):
            raise ValueError(
                f"physics model {self.name!r}: expected {len(self.parameters)} parameter "
                f"values {list(self.parameters)}, got {values.size}"
            )
        return dict(zip(self.parameters, values.tolist(), strict=True))

    def _call(self, arrays: dict[str, np.ndarray], n: int, params: dict[str, float]) -> np.ndarray:
        self.n_calls += 1
        try:
            out = self.function(dict(arrays), dict(params))
        except Exception as err:
            raise PhysicsModelError(
                f"physics function {self.name!r} raised {type(err).__name__}: {err} "
                f"at parameters {_format_params(params)}"
            ) from err
        out = np.asarray(out, dtype=float)
        if out.ndim == 0 and n == 1:
            out = out.reshape(1)
        if out.shape != (n,):
            raise PhysicsModelError(
                f"physics function {self.name!r} returned shape {out.shape}, expected ({n},) "
                f"(one value per data row) at parameters {_format_params(params)}"
            )
        return out

    def evaluate(
        self,
        inputs: Mapping[str, Any],
        params: Mapping[str, float] | Sequence[float],
        *,
        check_finite: bool = True,
    ) -> np.ndarray:
        """Run the model with numpy inputs and checks.

        Raises :class:`PhysicsModelError` naming the parameter values when the function
        raises, returns the wrong shape or (with ``check_finite``) NaN/inf.

        Examples
        --------
        >>> import numpy as np
        >>> from kohpymc.examples import beam
        >>> beam.physics_model().evaluate({"x": [400.0], "P": [2.5]}, {"E": 200.0})
        array([12.])
        """
        if self.backend == "pytensor":
            return self._evaluate_symbolic(inputs, params)
        arrays, n = self._as_inputs(inputs)
        p = self._as_params(params)
        out = self._call(arrays, n, p)
        if check_finite and not np.all(np.isfinite(out)):
            bad = int(np.sum(~np.isfinite(out)))
            raise PhysicsModelError(
                f"physics function {self.name!r} returned {bad} non-finite value(s) "
                f"at parameters {_format_params(p)}"
            )
        return out

    def _evaluate_symbolic(self, inputs, params) -> np.ndarray:
        arrays, n = self._as_inputs(inputs)
        p = self._as_params(params)
        X = np.column_stack([arrays[k] for k in self.inputs])
        theta = np.array([p[k] for k in self.parameters])
        out = self.tensor(pt.as_tensor_variable(theta), pt.as_tensor_variable(X)).eval()
        out = np.asarray(out, dtype=float).reshape(-1)
        if out.shape != (n,):
            raise PhysicsModelError(
                f"physics function {self.name!r} returned shape {out.shape}, expected ({n},)"
            )
        if not np.all(np.isfinite(out)):
            raise PhysicsModelError(
                f"physics function {self.name!r} returned non-finite values "
                f"at parameters {_format_params(p)}"
            )
        return out

    def jacobian_matrix(
        self, inputs: Mapping[str, Any], params: Mapping[str, float] | Sequence[float]
    ) -> np.ndarray:
        """``∂G/∂θ`` at the data rows, shape ``(n, p)`` (user Jacobian, FD or autodiff).

        Examples
        --------
        >>> from kohpymc.examples import beam
        >>> beam.physics_model().jacobian_matrix({"x": [400.0], "P": [2.5]}, {"E": 200.0})
        array([[-0.06]])
        """
        arrays, n = self._as_inputs(inputs)
        p = self._as_params(params)
        if self.backend == "pytensor":
            X = np.column_stack([arrays[k] for k in self.inputs])
            theta = pt.vector("theta", dtype="float64")
            out = self.tensor(theta, pt.as_tensor_variable(X))
            jac = pt.jacobian(out, theta)
            return np.asarray(jac.eval({theta: np.array(list(p.values()))}), dtype=float)
        return self._jacobian_numpy(arrays, n, p)

    def _jacobian_numpy(self, arrays, n, p: dict[str, float]) -> np.ndarray:
        names = list(self.parameters)
        if self.jacobian is not None:
            try:
                jac = self.jacobian(dict(arrays), dict(p))
            except Exception as err:
                raise PhysicsModelError(
                    f"jacobian of {self.name!r} raised {type(err).__name__}: {err} "
                    f"at parameters {_format_params(p)}"
                ) from err
            if isinstance(jac, Mapping):
                missing = [k for k in names if k not in jac]
                if missing:
                    raise PhysicsModelError(
                        f"jacobian of {self.name!r} lacks columns for parameters {missing}"
                    )
                jac = np.column_stack([np.asarray(jac[k], float).reshape(-1) for k in names])
            jac = np.asarray(jac, dtype=float)
            if jac.ndim == 1 and len(names) == 1:
                jac = jac[:, None]
            if jac.shape != (n, len(names)):
                raise PhysicsModelError(
                    f"jacobian of {self.name!r} returned shape {jac.shape}, "
                    f"expected ({n}, {len(names)})"
                )
            return jac
        return self.finite_difference_jacobian(arrays, p)

    def finite_difference_jacobian(
        self, inputs: Mapping[str, Any], params: Mapping[str, float]
    ) -> np.ndarray:
        """Finite-difference ``∂G/∂θ`` with the configured scheme and step.

        Examples
        --------
        >>> from kohpymc.examples import beam
        >>> J = beam.physics_model().finite_difference_jacobian(
        ...     {"x": [400.0], "P": [2.5]}, {"E": 200.0})
        >>> round(float(J[0, 0]), 6)
        -0.06
        """
        arrays, n = self._as_inputs(inputs)
        p = self._as_params(params)
        names = list(p)
        cols = []
        base = self._call(arrays, n, p) if self.fd_scheme == "forward" else None
        for name in names:
            h = self.fd_relative_step * max(abs(p[name]), self.parameters[name].scale())
            up = dict(p)
            up[name] = p[name] + h
            f_up = self._call(arrays, n, up)
            if self.fd_scheme == "central":
                down = dict(p)
                down[name] = p[name] - h
                cols.append((f_up - self._call(arrays, n, down)) / (2 * h))
            else:
                cols.append((f_up - base) / h)
        return np.column_stack(cols)

    # --------------------------------------------------------------- pytensor side
    def tensor(self, theta: pt.TensorVariable, X: pt.TensorVariable) -> pt.TensorVariable:
        """Symbolic ``G(X; θ)``.

        ``theta`` is a vector in parameter order, ``X`` an ``(n, d)`` matrix with columns
        in input order.

        Examples
        --------
        >>> import pytensor.tensor as pt
        >>> from kohpymc.examples import beam
        >>> physics = beam.physics_model()
        >>> float(physics.tensor(pt.as_tensor([200.0]), pt.as_tensor([[400.0, 2.5]])).eval()[0])
        12.0
        """
        theta = pt.as_tensor_variable(theta)
        X = pt.as_tensor_variable(X)
        if self.backend == "numpy":
            # a fresh Op per graph: reusing one Op instance in a second compiled model
            # made its sampling ~7x slower (beam M2 after M1 in one process: 211 s vs 33 s)
            op = _PhysicsOp(self)
            return op(pt.cast(theta, "float64"), pt.cast(X, "float64"))
        inputs = {k: X[:, j] for j, k in enumerate(self.inputs)}
        params = {k: theta[i] for i, k in enumerate(self.parameters)}
        out = self.function(inputs, params)
        out = pt.as_tensor_variable(out)
        # broadcast constant outputs to one value per row
        return pt.cast(out, "float64") + pt.zeros_like(X[:, 0], dtype="float64")

    def __repr__(self) -> str:
        return (
            f"PhysicsModel({self.name!r}, inputs={list(self.inputs)}, "
            f"parameters={self.parameters}, backend={self.backend!r})"
        )


class _PhysicsOpBase(Op):
    """Shared plumbing: inputs ``theta`` (p,) and ``X`` (n, d), gradient only in θ."""

    __props__ = ("physics",)
    output_ndim = 1

    def __init__(self, physics: PhysicsModel) -> None:
        self.physics = physics

    def make_node(self, theta, X):
        theta = pt.as_tensor_variable(theta)
        X = pt.as_tensor_variable(X)
        out = pt.vector if self.output_ndim == 1 else pt.matrix
        return Apply(self, [theta, X], [out(dtype="float64")])

    def _unpack(self, theta, X) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        physics = self.physics
        arrays = {k: np.asarray(X[:, j]) for j, k in enumerate(physics.inputs)}
        params = dict(zip(physics.parameters, np.asarray(theta, float).tolist(), strict=True))
        return arrays, params

    def connection_pattern(self, node):
        return [[True], [False]]


class _PhysicsOp(_PhysicsOpBase):
    """``G(X; θ)`` as a PyTensor Op: output (n,); gradient ``g @ ∂G/∂θ``."""

    def __init__(self, physics: PhysicsModel) -> None:
        super().__init__(physics)
        self.jacobian_op = _PhysicsJacobianOp(physics)

    def perform(self, node, inputs, outputs):
        theta, X = inputs
        arrays, params = self._unpack(theta, X)
        physics = self.physics
        out = physics._call(arrays, X.shape[0], params)
        if not np.all(np.isfinite(out)):
            if physics.on_nonfinite == "raise":
                raise PhysicsModelError(
                    f"physics function {physics.name!r} returned non-finite values at "
                    f"parameters {_format_params(params)} (pass on_nonfinite='reject' to "
                    "treat such points as having zero likelihood)"
                )
            out = np.where(np.isfinite(out), out, np.inf)
        outputs[0][0] = out

    def grad(self, inputs, output_grads):
        theta, X = inputs
        (g,) = output_grads
        return [pt.dot(g, self.jacobian_op(theta, X)), disconnected_type()]

    def infer_shape(self, fgraph, node, shapes):
        return [(shapes[1][0],)]


class _PhysicsJacobianOp(_PhysicsOpBase):
    """``∂G/∂θ`` as an Op: output (n, p), from the user's Jacobian or finite differences."""

    output_ndim = 2

    def perform(self, node, inputs, outputs):
        theta, X = inputs
        arrays, params = self._unpack(theta, X)
        outputs[0][0] = self.physics._jacobian_numpy(arrays, X.shape[0], params)

    def grad(self, inputs, output_grads):  # pragma: no cover - second derivatives unused
        raise NotImplementedError("second derivatives of a black-box physics model")

    def infer_shape(self, fgraph, node, shapes):
        return [(shapes[1][0], shapes[0][0])]
