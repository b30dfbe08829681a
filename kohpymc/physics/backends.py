"""How a physics function is run: one small strategy object per kind of function.

* :class:`NumpyBackend`: ``function(inputs, params)`` on numpy arrays and floats.  It is
  evaluated directly, its Jacobian is the user's ``jacobian`` or finite differences
  (:mod:`kohpymc.physics.finite_differences`), and in a graph it is a black-box
  :class:`~kohpymc.physics.ops._PhysicsOp` whose gradient is ``g @ J``.
* :class:`PytensorBackend`: ``function(inputs, params)`` written with
  ``pytensor.tensor`` operations.  It is put into the graph directly and gets exact
  automatic differentiation.

A backend holds no state: every method takes the :class:`~kohpymc.physics.PhysicsModel`
and reads its function, Jacobian and finite-difference settings when called.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import pytensor.tensor as pt

from kohpymc.physics.errors import NonFiniteOutputError, PhysicsModelError, format_params
from kohpymc.physics.finite_differences import finite_difference_jacobian
from kohpymc.physics.ops import _PhysicsOp

if TYPE_CHECKING:
    from kohpymc.physics.spec import PhysicsModel

__all__ = ["BACKENDS", "Backend", "NumpyBackend", "PytensorBackend", "call_function"]


def call_function(
    model: PhysicsModel, arrays: dict[str, np.ndarray], n: int, params: dict[str, float]
) -> np.ndarray:
    """One run of ``model.function`` on numpy values, counted in ``model.n_calls``.

    Raises :class:`PhysicsModelError` naming the parameter values when the function
    raises or does not return one value per row.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import PhysicsModel, Uniform
    >>> physics = PhysicsModel(lambda x, p: p["a"] * x["t"], {"a": Uniform(0, 1)}, ["t"])
    >>> call_function(physics, {"t": np.array([1.0, 2.0])}, 2, {"a": 0.5})
    array([0.5, 1. ])
    """
    model.n_calls += 1
    try:
        out = model.function(own_copies(arrays), dict(params))
    except Exception as err:
        raise PhysicsModelError(
            f"physics function {model.name!r} raised {type(err).__name__}: {err} "
            f"at parameters {format_params(params)}{unknown_key_hint(err, arrays, params)}"
        ) from err
    out = _real_values(model, out, params)
    if out.ndim == 0 and n == 1:
        out = out.reshape(1)
    if out.shape != (n,):
        raise PhysicsModelError(
            f"physics function {model.name!r} returned shape {out.shape}, expected ({n},) "
            f"(one value per data row) at parameters {format_params(params)}"
        )
    return out


def own_copies(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The input columns as fresh copies, for one call of a user's function.

    A function that converts units in place (``v = inputs["v"]; v *= 1e-3``) would
    otherwise change the data themselves, again at every call.

    Examples
    --------
    >>> data = {"v": np.array([1.0, 2.0])}
    >>> own_copies(data)["v"] *= 10
    >>> data["v"]
    array([1., 2.])
    """
    return {k: np.array(v, copy=True) for k, v in arrays.items()}


def _real_values(model: PhysicsModel, out: Any, params: dict[str, float]) -> np.ndarray:
    """``out`` as floats, refusing what a cast would silently change.

    Booleans and integers are steps in θ (no gradient, an identifiability check that
    finds the parameters without effect); a complex value with a nonzero imaginary part
    (``np.emath.sqrt`` of a negative number) would lose it in the cast; a dict, ``None``
    or text is not a column of numbers.
    """
    if isinstance(out, np.ndarray) and out.dtype == np.float64:
        return out  # the common case: no conversion, no message to prepare
    where = f"at parameters {format_params(params)}"
    try:
        raw = np.asarray(out)
    except ValueError as err:  # ragged nested lists
        raise PhysicsModelError(
            f"physics function {model.name!r} returned {type(out).__name__}, not an array of "
            f"numbers {where}: {err}"
        ) from err
    kind = raw.dtype.kind
    if kind in "biu":
        what = "booleans" if kind == "b" else f"integers ({raw.dtype})"
        raise PhysicsModelError(
            f"physics function {model.name!r} returned {what} {where}: an output that moves in "
            "whole steps does not vary smoothly with the parameters, so they cannot be "
            "calibrated; return floats (e.g. no rounding or astype(int))"
        )
    if kind == "c":
        imag = float(np.max(np.abs(raw.imag))) if raw.size else 0.0
        if imag > 0:
            raise PhysicsModelError(
                f"physics function {model.name!r} returned complex values (imaginary part up "
                f"to {imag:.3g}) {where}; a calibrated output must be real"
            )
        return np.asarray(raw.real, dtype=float)
    try:
        return np.asarray(raw, dtype=float)
    except (TypeError, ValueError) as err:
        raise PhysicsModelError(
            f"physics function {model.name!r} returned {type(out).__name__}, not an array of "
            f"numbers {where}: {err}"
        ) from err


def unknown_key_hint(err: Exception, arrays: Mapping, params: Mapping) -> str:
    """A sentence for a ``KeyError`` whose key is neither a parameter nor an input, else "".

    A function reading ``params["c"]`` when the priors declare ``damping``, or
    ``inputs["time"]`` when the input column is ``t``, fails with a bare ``KeyError: 'c'``;
    this names what the model does have.

    Examples
    --------
    >>> unknown_key_hint(KeyError("c"), {"t": 0}, {"k": 1.0, "damping": 0.1})
    "; 'c' is neither a parameter (k, damping) nor an input (t) of the model"
    >>> unknown_key_hint(KeyError("k"), {"t": 0}, {"k": 1.0})
    ''
    """
    if not isinstance(err, KeyError) or len(err.args) != 1:
        return ""
    key = err.args[0]
    if key in arrays or key in params:
        return ""
    return (
        f"; {key!r} is neither a parameter ({', '.join(map(str, params))}) nor an input "
        f"({', '.join(map(str, arrays))}) of the model"
    )


class Backend:
    """Evaluate, differentiate and build the tensor of one kind of physics function.

    ``arrays`` maps each input name to a 1-D array of length ``n``; ``params`` maps
    parameter names (in order) to floats.
    """

    kind: str = ""

    def evaluate(
        self,
        model: PhysicsModel,
        arrays: dict[str, np.ndarray],
        n: int,
        params: dict[str, float],
        *,
        check_finite: bool = True,
    ) -> np.ndarray:
        """``G`` at the rows, shape ``(n,)``."""
        raise NotImplementedError

    def jacobian(
        self, model: PhysicsModel, arrays: dict[str, np.ndarray], n: int, params: dict[str, float]
    ) -> np.ndarray:
        """``∂G/∂θ`` at the rows, shape ``(n, p)``."""
        raise NotImplementedError

    def tensor(
        self, model: PhysicsModel, theta: pt.TensorVariable, X: pt.TensorVariable
    ) -> pt.TensorVariable:
        """Symbolic ``G(X; θ)``, ``theta`` in parameter order, ``X`` columns in input order."""
        raise NotImplementedError


class NumpyBackend(Backend):
    """A numpy function: direct calls, user or finite-difference Jacobian, black-box Op.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import PhysicsModel, Uniform
    >>> physics = PhysicsModel(lambda x, p: p["a"] * x["t"], {"a": Uniform(0, 1)}, ["t"])
    >>> J = NumpyBackend().jacobian(physics, {"t": np.array([1.0, 2.0])}, 2, {"a": 0.5})
    >>> bool(np.allclose(J, [[1.0], [2.0]]))
    True
    """

    kind = "numpy"

    def call(
        self, model: PhysicsModel, arrays: dict[str, np.ndarray], n: int, params: dict[str, float]
    ) -> np.ndarray:
        """One checked run of the function (see :func:`call_function`)."""
        return call_function(model, arrays, n, params)

    def evaluate(
        self,
        model: PhysicsModel,
        arrays: dict[str, np.ndarray],
        n: int,
        params: dict[str, float],
        *,
        check_finite: bool = True,
    ) -> np.ndarray:
        """Run the function; with ``check_finite`` raise on NaN/inf."""
        out = self.call(model, arrays, n, params)
        if check_finite and not np.all(np.isfinite(out)):
            bad = int(np.sum(~np.isfinite(out)))
            raise NonFiniteOutputError(
                f"physics function {model.name!r} returned {bad} non-finite value(s) "
                f"at parameters {format_params(params)}"
            )
        return out

    def jacobian(
        self, model: PhysicsModel, arrays: dict[str, np.ndarray], n: int, params: dict[str, float]
    ) -> np.ndarray:
        """The user's ``jacobian`` (checked) or, without one, finite differences."""
        names = list(model.parameters)
        if model.jacobian is None:
            return finite_difference_jacobian(
                lambda q: self.call(model, arrays, n, q),
                params,
                {k: prior.scale() for k, prior in model.parameters.items()},
                scheme=model.fd_scheme,
                relative_step=model.fd_relative_step,
            )
        try:
            jac: Any = model.jacobian(own_copies(arrays), dict(params))
        except Exception as err:
            raise PhysicsModelError(
                f"jacobian of {model.name!r} raised {type(err).__name__}: {err} "
                f"at parameters {format_params(params)}{unknown_key_hint(err, arrays, params)}"
            ) from err
        if isinstance(jac, Mapping):
            missing = [k for k in names if k not in jac]
            if missing:
                raise PhysicsModelError(
                    f"jacobian of {model.name!r} lacks columns for parameters {missing}"
                )
            jac = np.column_stack([np.asarray(jac[k], float).reshape(-1) for k in names])
        jac = np.asarray(jac, dtype=float)
        if jac.ndim == 1 and len(names) == 1:
            jac = jac[:, None]
        if jac.shape != (n, len(names)):
            raise PhysicsModelError(
                f"jacobian of {model.name!r} returned shape {jac.shape}, "
                f"expected ({n}, {len(names)})"
            )
        return jac

    def tensor(
        self, model: PhysicsModel, theta: pt.TensorVariable, X: pt.TensorVariable
    ) -> pt.TensorVariable:
        """A black-box :class:`~kohpymc.physics.ops._PhysicsOp` applied to ``(θ, X)``."""
        # a fresh Op per graph: reusing one Op instance in a second compiled model
        # made its sampling ~7x slower (beam M2 after M1 in one process: 211 s vs 33 s)
        op = _PhysicsOp(model)
        return op(pt.cast(theta, "float64"), pt.cast(X, "float64"))


class PytensorBackend(Backend):
    """A function of ``pytensor.tensor`` operations: in the graph, exact autodiff.

    Examples
    --------
    >>> import numpy as np
    >>> import pytensor.tensor as pt
    >>> from kohpymc import PhysicsModel, Uniform
    >>> f = lambda x, p: p["a"] * pt.exp(x["t"])
    >>> physics = PhysicsModel(f, {"a": Uniform(0, 1)}, ["t"], backend="pytensor")
    >>> PytensorBackend().jacobian(physics, {"t": np.array([0.0])}, 1, {"a": 0.5})
    array([[1.]])
    """

    kind = "pytensor"

    def evaluate(
        self,
        model: PhysicsModel,
        arrays: dict[str, np.ndarray],
        n: int,
        params: dict[str, float],
        *,
        check_finite: bool = True,
    ) -> np.ndarray:
        """Evaluate the graph; always raises on NaN/inf (``check_finite`` is not used)."""
        X = np.column_stack([arrays[k] for k in model.inputs])
        theta = np.array([params[k] for k in model.parameters])
        out = self.tensor(model, pt.as_tensor_variable(theta), pt.as_tensor_variable(X))
        # one evaluation of a constant graph: PyTensor's Python implementations compile in
        # milliseconds, where the first C-backend function of a process took 1-4 s
        values = np.asarray(out.eval(mode="FAST_COMPILE"), dtype=float).reshape(-1)
        if values.shape != (n,):
            raise PhysicsModelError(
                f"physics function {model.name!r} returned shape {values.shape}, expected ({n},)"
            )
        if not np.all(np.isfinite(values)):
            raise NonFiniteOutputError(
                f"physics function {model.name!r} returned non-finite values "
                f"at parameters {format_params(params)}"
            )
        return values

    def jacobian(
        self, model: PhysicsModel, arrays: dict[str, np.ndarray], n: int, params: dict[str, float]
    ) -> np.ndarray:
        """``pt.jacobian`` of the graph with respect to θ."""
        X = np.column_stack([arrays[k] for k in model.inputs])
        theta = pt.vector("theta", dtype="float64")
        out = self.tensor(model, theta, pt.as_tensor_variable(X))
        jac = pt.jacobian(out, theta)
        values = {theta: np.array(list(params.values()))}
        return np.asarray(jac.eval(values, mode="FAST_COMPILE"), dtype=float)

    def tensor(
        self, model: PhysicsModel, theta: pt.TensorVariable, X: pt.TensorVariable
    ) -> pt.TensorVariable:
        """``model.function`` on the columns of ``X`` and entries of ``θ``, one value per row."""
        inputs = {k: X[:, j] for j, k in enumerate(model.inputs)}
        params = {k: theta[i] for i, k in enumerate(model.parameters)}
        out = model.function(inputs, params)
        out = pt.as_tensor_variable(out)
        # broadcast constant outputs to one value per row
        return pt.cast(out, "float64") + pt.zeros_like(X[:, 0], dtype="float64")


#: backend name (the ``backend=`` argument of ``PhysicsModel``) -> strategy
BACKENDS: dict[str, Backend] = {"numpy": NumpyBackend(), "pytensor": PytensorBackend()}
