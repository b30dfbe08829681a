r"""Nutpie's native path: the log density in the sampling coordinates as one numba function.

:mod:`kohpymc.sampling` samples the whitened coordinates ``z`` of
:class:`~kohpymc.reparameterization.Reparameterization`.  Through a Python callback
every evaluation crosses Rust → Python → numpy (the map ``z → v``) → a compiled
PyTensor function, ~70 µs on the beam of which the model's graph is ~5 µs.  When the
model's log density is pure PyTensor (no Python ``perform`` that numba would run in
object mode, e.g. a numpy physics function) this module instead builds the whole
density symbolically — the affine map ``u = μ + L z``, the bound ridge, the variance
shares and the elementwise coordinates (the same formulas as the numpy map, written
once over :class:`~kohpymc.reparameterization.ArrayMath`), then the model's
``logp`` at ``v(z)`` plus ``log|dv/dw|`` — and hands it, with its PyTensor gradient,
to nutpie's Rust sampler as a numba C function: no Python runs per evaluation and
chains run on threads without the GIL.  Nutpie keeps ``z``; :func:`expand_draws` maps
the kept draws to the user's parameters and deterministics afterwards.

:func:`python_only_ops` says why a model cannot take this path; :func:`native_model`
raises when it cannot compile (the caller then uses the Python callback and records
why).
"""

from __future__ import annotations

import functools
import hashlib
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numba
import numpy as np
import pytensor
import pytensor.tensor as pt
from llvmlite import ir as llvm_ir  # type: ignore[import-untyped]  # llvmlite ships no stubs
from numba.extending import intrinsic
from pymc.pytensorf import replace_vars_in_graphs
from pytensor.compile.sharedvalue import SharedVariable
from pytensor.graph.traversal import applys_between, graph_inputs

from kohpymc.graph_cache import compile_cached
from kohpymc.reparameterization import ArrayMath, Coordinates, Reparameterization
from kohpymc.value_space import NumbaDensity, ValueSpace, value_logp

__all__ = [
    "PYTENSOR",
    "density_in_z",
    "expand_draws",
    "map_in_z",
    "native_model",
    "parameters",
    "python_only_ops",
    "symbolic_value",
]

#: :class:`~kohpymc.reparameterization.ArrayMath` building PyTensor graphs
PYTENSOR = ArrayMath(
    pt.exp, pt.expm1, pt.log, pt.sigmoid, pt.logaddexp, pt.dot, pt.switch, pt.all, pt.sum,
    lambda x: x,
    lambda out, index, value: pt.set_subtensor(out[index], value),
    lambda out, index, value: pt.inc_subtensor(out[index], value),
)  # fmt: skip

#: prefix of the helper variables ``z`` and ``θ`` (never a user's name)
_PREFIX = "__kohpymc_native_"
#: name of the sampling coordinates ``z`` in nutpie's draws, before :func:`expand_draws`
KEPT_DRAWS = f"{_PREFIX}z"


def python_only_ops(graphs: Sequence[Any]) -> list[str]:
    """Ops in ``graphs`` that numba would run in object mode (Python ``perform``).

    An Op counts when numba has no implementation registered for its type (PyTensor
    then calls ``perform`` from Python, e.g. the numpy physics Ops); the inner graphs
    of :class:`~pytensor.compile.builders.OpFromGraph` and the core Ops of
    :class:`~pytensor.tensor.blockwise.Blockwise` are looked into.  (Implementations
    that fall back to object mode for some inputs only show when compiling:
    :func:`native_model` turns that warning into an error.)

    Examples
    --------
    >>> import pytensor.tensor as pt
    >>> x = pt.vector("x")
    >>> python_only_ops([pt.exp(x).sum()])
    []
    """
    found: list[str] = []
    for node in applys_between([], list(graphs)):
        found.extend(_python_only(node.op))
    return sorted(set(found))


def _python_only(op: Any) -> list[str]:
    """:func:`python_only_ops` of one Op."""
    from pytensor.compile.builders import OpFromGraph
    from pytensor.link.numba.dispatch import basic
    from pytensor.tensor.blockwise import Blockwise

    if isinstance(op, OpFromGraph):
        return python_only_ops(op.inner_outputs)
    if isinstance(op, Blockwise):
        return _python_only(op.core_op)
    # PyTensor registers numba implementations in any of three dispatchers
    registries = (
        basic.numba_funcify,
        basic.numba_funcify_default_op_cache_key,
        basic.numba_funcify_and_cache_key,
    )
    if all(r.dispatch(type(op)) is r.dispatch(object) for r in registries):
        return [type(op).__name__]
    return []


def symbolic_value(
    mapping: Reparameterization,
    z: Any,
    *,
    mean: Any = None,
    chol: Any = None,
    constants: Any = None,
) -> tuple[Any, Any]:
    """``v(z)`` and ``log|dv/dz|`` (constant terms left out) as PyTensor graphs.

    The same map as :meth:`Reparameterization.to_value` and the Jacobian term of
    :meth:`Reparameterization.logp_dlogp`; ``mean``, ``chol`` and ``constants`` (the
    plan's :meth:`~Reparameterization.map_constants`; default: the plan's, as constants)
    may be variables holding them.

    Examples
    --------
    >>> from kohpymc.reparameterization import Coordinates
    >>> plan = Reparameterization("affine", np.ones(2), 2 * np.eye(2),
    ...                           Coordinates.identity(2), "")
    >>> v, _ = symbolic_value(plan, pt.as_tensor(np.array([0.5, -1.0])))
    >>> v.eval()
    array([ 2., -1.])
    """
    mean = mapping.mean if mean is None else mean
    chol = mapping.chol if chol is None else chol
    if constants is not None:
        mapping = mapping.with_map_constants(constants)
    return mapping.value_from_affine(mean + pt.dot(chol, z), PYTENSOR)


def _map_size(mapping: Reparameterization) -> int:
    """Length of the plan's part of θ: ``μ``, ``vec L`` and its map constants."""
    n = mapping.ndim
    return n + n * n + int(mapping.map_constants().size)


def _symbolic_map(mapping: Reparameterization, z: Any, m: Any) -> tuple[Any, Any]:
    """:func:`symbolic_value` with the plan's numbers read from the vector ``m``."""
    n = mapping.ndim
    return symbolic_value(
        mapping, z, mean=m[:n], chol=m[n : n + n * n].reshape((n, n)), constants=m[n + n * n :]
    )


def _value_replacements(space: ValueSpace, v: Any) -> dict[Any, Any]:
    """The model's value variables as slices of the flat vector ``v``."""
    out, start = {}, 0
    for var, shape in zip(space.model.value_vars, space.shapes, strict=True):
        size = int(np.prod(shape, dtype=int))
        out[var] = v[start : start + size].reshape(shape).astype(var.dtype)
        start += size
    return out


def density_in_z(
    space: ValueSpace, mapping: Reparameterization
) -> tuple[Any, Any, Any, Any, list[Any]]:
    """``z``, the parameters ``θ`` and the log density in ``z`` with its gradient.

    ``log p(v(z)) + log|dv/dz|`` (constant terms left out, as
    :meth:`Reparameterization.logp_dlogp`).  ``θ`` is a second input holding the plan's
    ``μ``, ``L`` and map constants and the values of the model's float shared variables
    (e.g. data swapped in by :func:`kohpymc.sbc.check_calibration`), returned last, in
    :func:`parameters`' order; other shared variables are frozen as constants.  So the
    graph — and numba's disk cache of it — does not change with the plan or the data.

    Examples
    --------
    >>> z, theta, logp, grad, shared = density_in_z(space, plan)  # doctest: +SKIP
    >>> f = pytensor.function([z, theta], [logp, grad])  # doctest: +SKIP
    >>> f(np.zeros(space.ndim), parameters(plan, shared))  # doctest: +SKIP
    """
    n = space.ndim
    logp = value_logp(space.model)
    shared = [var for var in graph_inputs([logp]) if isinstance(var, SharedVariable)]
    packed = [var for var in shared if getattr(var.type, "dtype", None) == "float64"]
    sizes = [int(np.size(var.get_value())) for var in packed]
    z = pt.TensorType("float64", shape=(n,))(f"{_PREFIX}z")
    start = _map_size(mapping)
    theta = pt.TensorType("float64", shape=(start + sum(sizes),))(f"{_PREFIX}theta")
    replacements: dict[Any, Any] = {
        var: pt.constant(var.get_value(), dtype=getattr(var.type, "dtype", None))
        for var in shared
        if var not in packed
    }
    for var, size in zip(packed, sizes, strict=True):
        shape = np.shape(var.get_value())
        replacements[var] = pt.specify_shape(theta[start : start + size].reshape(shape), shape)
        start += size
    v, logjac = _symbolic_map(mapping, z, theta[: _map_size(mapping)])
    replacements.update(_value_replacements(space, v))
    (logp,) = replace_vars_in_graphs([logp], replacements)
    logp = logp + logjac
    return z, theta, logp, pytensor.grad(logp, z), packed


def parameters(mapping: Reparameterization, shared: Sequence[Any] = ()) -> np.ndarray:
    """``θ`` of :func:`density_in_z`: ``μ``, ``vec L``, map constants, ``shared`` values.

    One C-contiguous vector.

    Examples
    --------
    >>> from kohpymc.reparameterization import Coordinates
    >>> plan = Reparameterization("affine", np.ones(1), 2 * np.eye(1),
    ...                           Coordinates.identity(1), "")
    >>> parameters(plan)
    array([1., 2.])
    """
    values = [np.ravel(mapping.mean), np.ravel(mapping.chol), mapping.map_constants()]
    values += [np.ravel(var.get_value()) for var in shared]
    return np.ascontiguousarray(np.concatenate(values), dtype=float)


def native_model(
    space: ValueSpace, mapping: Reparameterization, initial_point: Callable[[int], np.ndarray]
):
    """Nutpie's numba-compiled model of ``z`` for ``space`` sampled through ``mapping``.

    The log density and gradient in ``z`` (:func:`density_in_z`) become one numba C
    function that reads ``θ`` (:func:`parameters`) from nutpie's user-data pointer;
    its source and numba's object code are cached on disk under a key of the graph, so
    a later process with the same model loads it instead of compiling (~10 s per beam
    formulation).  The
    draws nutpie keeps are ``z`` itself (a cached copy function); :func:`expand_draws`
    maps them to the user's parameters after sampling.

    Parameters
    ----------
    space : ValueSpace
    mapping : Reparameterization
    initial_point : callable
        ``seed -> z``, each chain's start.

    Returns
    -------
    nutpie.compile_pymc.CompiledPyMCModel

    Raises
    ------
    ValueError
        When the graph holds an Op numba can only run from Python.
    NotImplementedError
        When ``mapping`` is a plan with its own numpy map (e.g. a
        :class:`~kohpymc.reparameterization.BoxRidgePlan`), which has no symbolic form.
    Exception
        Whatever the compilation raises.

    Examples
    --------
    >>> compiled = native_model(space, plan, lambda seed: np.zeros(space.ndim))  # doctest: +SKIP
    """
    from nutpie import compile_pymc as ncp

    if not mapping.symbolic:
        raise NotImplementedError(f"no symbolic form of a {type(mapping).__name__}'s map")
    composed = _composed_logp(space, mapping)  # the space's density has no Python-only Op
    if composed is not None:
        logp_c, function, user_data = composed
    else:
        python_ops = python_only_ops([value_logp(space.model)])
        if python_ops:  # before any compiling (a numpy physics model's usual case)
            raise ValueError(f"Python-only Op(s) in the log density: {', '.join(python_ops)}")
        z, theta, logp, grad, shared = density_in_z(space, mapping)
        python_ops = python_only_ops([logp, grad])  # e.g. a Python Op in a gradient only
        if python_ops:
            raise ValueError(f"Python-only Op(s) in the log density: {', '.join(python_ops)}")
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message="Numba will use object mode")
            function = compile_cached([z, theta], [logp, grad], mode="NUMBA")
            logp_c = _logp_cfunc(function.vm.jit_fn, space.ndim, int(theta.type.shape[0]))
        user_data = parameters(mapping, shared)
    n = space.ndim
    z_name = KEPT_DRAWS
    return ncp.CompiledPyMCModel(
        _n_dim=n,
        dims={},
        _coords={},
        _shapes={z_name: (n,)},
        compiled_logp_func=logp_c,
        compiled_expand_func=_copy_draw(),
        initial_point_func=initial_point,
        shared_data={},
        user_data=user_data,
        n_expanded=n,
        shape_info=([z_name], [slice(0, n)], [(n,)]),
        logp_func=function,
        expand_func=None,
    )


def map_in_z(mapping: Reparameterization, n: int) -> tuple[Any, Any, Any, list[Any]]:
    """The map ``z -> v`` with ``log|dv/dz|`` and the gradient of a density through it.

    Inputs ``z``, ``m`` (the plan's ``μ``, ``vec L`` and map constants, :func:`parameters`
    without shared values) and ``g``; outputs ``v(z)``, ``log|dv/dz|`` and
    ``(∂v/∂z)ᵀ g + ∂ log|dv/dz| / ∂z``: with ``g = ∇ log p(v)`` the gradient of
    ``log p(v(z)) + log|dv/dz|`` in ``z``.  A graph of a few dozen nodes, which lets
    :func:`native_model` reuse the model's compiled density (:class:`NumbaDensity`)
    instead of compiling the model's graph again inside ``log p(v(z))``.

    Returns ``(z, m, g, outputs)``.

    Examples
    --------
    >>> from kohpymc.reparameterization import Coordinates
    >>> plan = Reparameterization("affine", np.zeros(1), 2 * np.eye(1),
    ...                           Coordinates.identity(1), "")
    >>> z, m, g, outputs = map_in_z(plan, 1)
    >>> f = pytensor.function([z, m, g], outputs)
    >>> [np.asarray(a).tolist() for a in f([0.5], [0.0, 2.0], [3.0])]
    [[1.0], 0.0, [6.0]]
    """
    z = pt.TensorType("float64", shape=(n,))(f"{_PREFIX}z")
    m = pt.TensorType("float64", shape=(_map_size(mapping),))(f"{_PREFIX}map")
    g = pt.TensorType("float64", shape=(n,))(f"{_PREFIX}gradient")
    v, logjac = _symbolic_map(mapping, z, m)
    logjac = pt.as_tensor_variable(logjac).astype("float64")
    grad = pytensor.grad(pt.dot(v, g) + logjac, z)
    return z, m, g, [v, logjac, grad]


#: the body of :func:`_composed_logp`'s C function: ``v(z)``, the density at ``v`` (the
#: space's compiled C function, its address and shared values after the map in the user
#: data), the gradient back in ``z``
_COMPOSED_BODY = """
m = theta[:N_MAP]
v, logjac, _ = map_fn(x, m, np.zeros(N_DIM))
v = np.ascontiguousarray(v)
grad_v = np.empty(N_DIM)
value = np.empty(1)
address = theta[N_MAP : N_MAP + 1].view(np.int64)[0]
shared = theta.ctypes.data + 8 * (N_MAP + 1)
if call_density(address, v.ctypes.data, shared, grad_v.ctypes.data, value.ctypes.data) != 1:
    raise ValueError("the log density raised")
_, _, grad = map_fn(x, m, grad_v)
logp[()] = value[0] + logjac
out[...] = grad
"""


@intrinsic
def call_density(typingctx: Any, address: Any, x: Any, theta: Any, out: Any, logp: Any) -> Any:
    """Call the C function at ``address`` (:data:`~kohpymc.value_space.DENSITY_SIGNATURE`).

    The arguments are addresses (integers); numba links nothing of the callee, so a
    function calling the model's compiled density this way compiles in the time of its
    own code, and caches on disk (the address is read at each call).
    """
    args = (address, x, theta, out, logp)
    if not all(isinstance(arg, numba.types.Integer) for arg in args):
        return None
    pointer = llvm_ir.DoubleType().as_pointer()

    def codegen(context: Any, builder: Any, signature: Any, values: Any) -> Any:
        function_type = llvm_ir.FunctionType(llvm_ir.IntType(64), [pointer] * 4)
        function = builder.inttoptr(values[0], function_type.as_pointer())
        return builder.call(function, [builder.inttoptr(v, pointer) for v in values[1:]])

    return numba.types.int64(*args), codegen


def _composed_logp(space: ValueSpace, mapping: Reparameterization) -> tuple[Any, Any, Any] | None:
    """Nutpie's C function as ``map_in_z`` around the space's compiled density, or None.

    A plain plan (affine, with elementwise coordinates and variance shares, no bound
    ridge) takes :func:`_affine_logp_c`, one C function whose user data hold the whole
    map (:func:`_affine_user_data`): compiled once for every dimension and model (the
    beam study's five formulations compiled five maps before, ~17 s from empty caches),
    and no map function is returned.  Other plans compile their map:
    returns ``(C function, the map's compiled function, user data)``: the user data are
    the plan's ``μ``, ``vec L`` and map constants, the address of the space's density
    (:attr:`~kohpymc.value_space.NumbaDensity.c_function`, its bits as one float64) and
    its shared values.  The C function holds the map only (the model's graph is
    compiled once, in the density), so its disk cache serves every model with the same
    plan structure.  ``None`` when the space's density is not a :class:`NumbaDensity`
    with a C function (the caller then compiles the whole density in ``z``,
    :func:`density_in_z`).
    """
    from pytensor.link.numba.cache import CACHED_SRC_FUNCTIONS

    density = space._logp_dlogp
    if not isinstance(density, NumbaDensity) or density.c_function is None:
        return None
    user_data = _affine_user_data(mapping, density)
    if user_data is not None:  # one compiled function for every plain plan
        return _affine_logp_c(), None, user_data
    n = space.ndim
    z, m, g, outputs = map_in_z(mapping, n)
    function = compile_cached([z, m, g], outputs, mode="NUMBA")  # the rewrites kept on disk
    map_jit = function.vm.jit_fn
    n_map = _map_size(mapping)
    map_key = CACHED_SRC_FUNCTIONS.get(map_jit.py_func)
    key = None
    if map_key is not None:  # the density's shared values (after the address) are not read
        parts = f"{map_key}-{n}-{n_map}".encode()
        key = f"kohpymc-native-composed-v5-{hashlib.sha256(parts).hexdigest()}"  # a file name
    names = {"N_MAP": n_map, "map_fn": _inlined(map_jit), "call_density": call_density}
    logp_c = _logp_c(_COMPOSED_BODY, n, n_map + 1, names, key)
    values = [parameters(mapping)[:n_map], _address_bits(density), density.theta()]
    return logp_c, function, np.ascontiguousarray(np.concatenate(values))


def _address_bits(density: NumbaDensity) -> np.ndarray:
    """The address of ``density``'s C function as one float64 with its bits (user data)."""
    return np.array([density.c_function.address], dtype=np.int64).view(np.float64)


#: nutpie's log-density C signature: (dim, x, gradient out, logp out, user data) -> code
_LOGP_SIGNATURE = numba.types.int64(
    numba.types.uint64,
    numba.types.CPointer(numba.types.double),
    numba.types.CPointer(numba.types.double),
    numba.types.CPointer(numba.types.double),
    numba.types.voidptr,
)

#: nutpie's log-density C function; ``body`` (a numba function of ``x``, ``theta`` (the user
#: data), ``out`` and ``logp``) sets ``logp[()]`` and ``out``, the gradient.  Return codes are
#: those of nutpie's own wrapper (1: the body raised, 3: non-finite gradient, 4: non-finite
#: density).  Only the call is inside ``try``: numba's exception handling around the inlined
#: graph itself made the first compile ~2× slower (emulated dielectric: 19 s CPU against 9.5 s).
_LOGP_TEMPLATE = """
def logp_c(dim, x_, out_, logp_, user_data_):
    if dim != N_DIM:
        return -1
    x = carray(x_, (N_DIM,))
    out = carray(out_, (N_DIM,))
    logp = carray(logp_, ())
    theta = carray(user_data_, (N_THETA,), float64)
    try:
        body(x, theta, out, logp)
    except Exception:
        return 1
    return status(out, logp)
"""


@numba.njit(cache=True)
def _status(out, logp):  # pragma: no cover - runs compiled
    """Nutpie's return code after a density evaluated: 3 non-finite gradient, 4 density."""
    if not np.all(np.isfinite(out)):
        return 3
    if not np.isfinite(logp[()]):
        return 4
    return 0


def _logp_c(body: str, n_dim: int, n_theta: int, names: dict[str, Any], key: str | None) -> Any:
    """Nutpie's C function :data:`_LOGP_TEMPLATE` around ``body``, compiled by numba.

    ``body``: the statements of a function of ``x``, ``theta``, ``out`` and ``logp``;
    ``names``: what they call, besides ``np``, ``N_DIM`` and ``N_THETA``.  Both functions
    are cached on disk under ``key`` (a file name) when it is not ``None``.
    """
    from pytensor.link.numba.cache import compile_numba_function_src
    from pytensor.link.numba.dispatch.basic import numba_njit

    lines = body.strip("\n").splitlines()
    source = "def body(x, theta, out, logp):\n" + "\n".join(" " * 4 + line for line in lines)
    # numba rebuilds a cached function's environment from an importable module
    env = {"N_DIM": n_dim, "N_THETA": n_theta, "np": np, "__name__": __name__, **names}
    body_key = None if key is None else f"{key}-body"
    raw_body = compile_numba_function_src(source, "body", env, cache_key=body_key)
    env = {
        "N_DIM": n_dim,
        "N_THETA": n_theta,
        "carray": numba.carray,
        "float64": numba.float64,
        "np": np,
        "__name__": __name__,
        "body": numba_njit(raw_body, cache=key is not None),
        "status": _status,
    }
    raw = compile_numba_function_src(_LOGP_TEMPLATE, "logp_c", env, cache_key=key)
    return numba.cfunc(_LOGP_SIGNATURE, cache=key is not None)(raw)


def _logp_cfunc(jit_fn: Any, n_dim: int, n_theta: int) -> Any:
    """Nutpie's log-density C function around PyTensor's numba function ``jit_fn``.

    Its return codes are those of nutpie's own wrapper (see :data:`_LOGP_TEMPLATE`).
    Cached on disk, keyed by PyTensor's key of the graph, when that has one.
    """
    from pytensor.link.numba.cache import CACHED_SRC_FUNCTIONS

    graph_key = CACHED_SRC_FUNCTIONS.get(jit_fn.py_func)
    key = None if graph_key is None else f"kohpymc-native-logp-v6-{graph_key}-{n_dim}-{n_theta}"
    body = "value, grad = jit_fn(x, theta)\nlogp[()] = value\nout[...] = grad"
    return _logp_c(body, n_dim, n_theta, {"jit_fn": _inlined(jit_fn)}, key)


def _inlined(jit_fn: Any) -> Any:
    """PyTensor's graph function behind ``jit_fn``, inlined into its caller by numba.

    ``jit_fn`` calls the graph's function through a wrapper, and numba generates the
    machine code of everything a function calls once per level (~1 s per level and beam
    formulation from an empty cache: 45 → 33 s CPU for M0–M4); inlined, the graph is
    generated once, with the C function nutpie calls.  ``jit_fn`` itself when its
    structure is not PyTensor's (the wrapper's global ``jitable_func``).
    """
    from pytensor.link.numba.dispatch.basic import numba_njit

    graph_fn = getattr(jit_fn, "py_func", None)
    inner = getattr(graph_fn, "__globals__", {}).get("jitable_func")
    if inner is None or getattr(inner, "py_func", None) is None:
        return jit_fn
    return numba_njit(inner.py_func, inline="always")


@functools.cache
def _copy_draw():
    """Nutpie's expand C function that keeps ``z`` as it is (compiled once, cached)."""
    signature = numba.types.int64(
        numba.types.uint64,
        numba.types.uint64,
        numba.types.CPointer(numba.types.double),
        numba.types.CPointer(numba.types.double),
        numba.types.voidptr,
    )
    return numba.cfunc(signature, cache=True)(_copy)


def _copy(dim, expanded, x_, out_, user_data_):  # pragma: no cover - runs compiled
    if dim != expanded:
        return -1
    x = numba.carray(x_, (dim,))
    out = numba.carray(out_, (dim,))
    out[:] = x
    return 0


def expand_draws(
    idata: Any,
    space: ValueSpace,
    mapping: Reparameterization,
    coords: dict[str, Any],
    dims: dict[str, tuple[str, ...]],
) -> Any:
    """``idata`` with its posterior of ``z`` replaced by the user's parameters (in place).

    Each draw goes through ``mapping.to_value`` and ``space.expand`` (all draws at once:
    :meth:`ValueSpace.expand_rows`), as the Python callback path's expand function does;
    dims and coords as there.
    """
    import xarray as xr

    z = idata.posterior[KEPT_DRAWS].values
    chains, draws = z.shape[:2]
    rows = np.array([mapping.to_value(point) for point in z.reshape(chains * draws, -1)])
    values = space.expand_rows(rows)
    variables = {}
    for key, shape in zip(space.expanded_names, space.expanded_shapes, strict=True):
        array = values[key].reshape(chains, draws, *shape)
        var_dims = dims.get(key) or tuple(f"{key}_dim_{i}" for i in range(len(shape)))
        variables[key] = (("chain", "draw", *var_dims), array)
    used = {d for _, (var_dims, _) in variables.items() for d in var_dims}
    posterior = xr.Dataset(
        variables,
        coords={
            "chain": idata.posterior["chain"].values,
            "draw": idata.posterior["draw"].values,
            **{k: np.asarray(v) for k, v in coords.items() if k in used},
        },
        attrs=dict(idata.posterior.attrs),
    )
    idata.posterior = posterior
    return idata


# --- one C function for every plain plan: the map's structure in the user data -------------

#: :func:`_affine_user_data`'s header: total length, density address, dimension, walls flag,
#: number of variance-share pairs, start of the density's shared values
_HEADER = 6


def _affine_user_data(mapping: Reparameterization, density: NumbaDensity) -> np.ndarray | None:
    """The user data of :func:`_affine_logp_c` for ``mapping`` around ``density``, or None.

    The plan's whole map is data: a header (:data:`_HEADER`), ``μ``, ``L`` (row-major),
    the elementwise coordinates (log-scale flags, lower and upper bounds), the
    variance-share pairs ``(i, j, c)``, then the density's shared values.  None for a
    plan this generic map does not cover (a subclass with its own map or map constants,
    a bound ridge, elementwise coordinates of a subclass): those compile their own map
    (:func:`_composed_logp`).
    """
    coords = mapping.coordinates
    if type(mapping) is not Reparameterization or coords.ridge is not None:
        return None
    if type(coords) is not Coordinates:  # elementwise maps of its own (e.g. a soft box)
        return None
    n = mapping.ndim
    pairs = () if coords.shares is None else coords.shares.pairs
    parts = [
        np.ravel(mapping.mean), np.ravel(mapping.chol), coords.log_scale.astype(float),
        np.nan_to_num(coords.lower, nan=1.0), np.nan_to_num(coords.upper, nan=2.0),
        np.ravel(np.array(pairs, dtype=float)),
    ]  # fmt: skip
    start = _HEADER + sum(p.size for p in parts)
    shared = density.theta()
    address = _address_bits(density)[0]
    header = [start + shared.size, address, n, float(coords.walls), len(pairs), start]
    return np.ascontiguousarray(np.concatenate([header, *parts, shared]), dtype=float)


@numba.njit(cache=True)
def _expit(t):  # pragma: no cover - runs compiled
    if t >= 0.0:
        return 1.0 / (1.0 + np.exp(-t))
    e = np.exp(t)
    return e / (1.0 + e)


@numba.njit(cache=True)
def _softplus(t):  # pragma: no cover - runs compiled
    return max(t, 0.0) + np.log1p(np.exp(-abs(t)))


@numba.njit(error_model="numpy", cache=True)
def _elementwise(theta, w, v, dv, dlogjac):  # pragma: no cover - runs compiled
    """``v(w)``, ``dv/dw`` and ``d log|dv/dw| / dw`` in place; returns ``Σ log|dv/dw|``.

    The formulas of :meth:`~kohpymc.reparameterization.Coordinates.to_value`; ``-inf``
    outside a wall.
    """
    n = w.size
    flags, lower, upper = _HEADER + n + n * n, _HEADER + 2 * n + n * n, _HEADER + 3 * n + n * n
    walls = theta[3] != 0.0
    logjac = 0.0
    for i in range(n):
        v[i], dv[i], dlogjac[i] = w[i], 1.0, 0.0
        if theta[flags + i] == 0.0:
            continue
        a, b = theta[lower + i], theta[upper + i]
        if walls:
            x = np.exp(w[i])
            above, below = x - a, b - x
            if not (above > 0.0 and below > 0.0):
                return -np.inf
            g = x * (b - a) / (above * below)
            dlogjac[i] = 1.0 - x / above + x / below
        else:
            c = np.log(b) - np.log(a)
            s = _expit(w[i])
            x = np.exp(np.log(a) + c * s)
            above = a * np.expm1(c * s)
            below = -b * np.expm1(-c * (1.0 - s))
            ds = s * (1.0 - s)
            g = (b - a) / (above * below) * x * c * ds
            dlogjac[i] = (2 * x - a - b) / (above * below) * x * c * ds + c * ds + 1.0 - 2.0 * s
        v[i], dv[i] = np.log(above) - np.log(below), g
        logjac += np.log(g)
    return logjac


@numba.njit(error_model="numpy", cache=True)
def _affine_body(x, theta, out):  # pragma: no cover - runs compiled
    """``log p(v(z)) + log|dv/dz|`` at ``z = x``, its gradient into ``out``.

    ``u = μ + L z``; the variance shares (:class:`~kohpymc.reparameterization.VarianceShare`)
    take ``u`` to ``w``; the elementwise coordinates ``w`` to ``v``; the density's C
    function (its address in ``theta``) gives ``log p(v)`` and ``∇ log p``, pulled back
    to ``z`` as :meth:`Reparameterization.logp_dlogp` does.
    """
    n = x.size
    mean, chol = _HEADER, _HEADER + n
    u = np.empty(n)
    for i in range(n):
        total = theta[mean + i]
        for j in range(n):
            total += theta[chol + i * n + j] * x[j]
        u[i] = total
    pairs, n_pairs = _HEADER + 4 * n + n * n, int(theta[4])
    w = u.copy()
    for k in range(n_pairs):
        i, j, c = int(theta[pairs + 3 * k]), int(theta[pairs + 3 * k + 1]), theta[pairs + 3 * k + 2]
        log_a = u[i] - 0.5 * _softplus(2.0 * u[j])
        w[i], w[j] = log_a, c * (log_a + u[j])
    v, dv, dlogjac = np.empty(n), np.empty(n), np.empty(n)
    logjac = _elementwise(theta, w, v, dv, dlogjac)
    if logjac == -np.inf:  # outside a wall: zero density
        out[:] = 0.0
        return -np.inf
    grad_v, value = np.empty(n), np.empty(1)
    address = theta[1:2].view(np.int64)[0]
    shared = theta.ctypes.data + 8 * int(theta[5])
    if call_density(address, v.ctypes.data, shared, grad_v.ctypes.data, value.ctypes.data) != 1:
        raise ValueError("the log density raised")
    grad_w = grad_v * dv + dlogjac
    grad_u = grad_w.copy()
    for k in range(n_pairs):
        i, j, c = int(theta[pairs + 3 * k]), int(theta[pairs + 3 * k + 1]), theta[pairs + 3 * k + 2]
        s = _expit(2.0 * u[j])
        grad_u[i] = grad_w[i] + c * grad_w[j]
        grad_u[j] = -s * grad_w[i] + c * (1.0 - s) * grad_w[j]
    for j in range(n):
        total = 0.0
        for i in range(n):
            total += theta[chol + i * n + j] * grad_u[i]
        out[j] = total
    return value[0] + logjac


def _affine_logp(dim, x_, out_, logp_, user_data_):  # pragma: no cover - runs compiled
    """Nutpie's C function of :func:`_affine_body`; return codes as :data:`_LOGP_TEMPLATE`."""
    header = numba.carray(user_data_, (_HEADER,), numba.float64)
    if int(header[2]) != dim:
        return -1
    theta = numba.carray(user_data_, (int(header[0]),), numba.float64)
    x = numba.carray(x_, (dim,))
    out = numba.carray(out_, (dim,))
    logp = numba.carray(logp_, ())
    try:
        logp[()] = _affine_body(x, theta, out)
    except Exception:
        return 1
    return _status(out, logp)


@functools.cache
def _affine_logp_c() -> Any:
    """:func:`_affine_logp` as a C function, compiled once (or loaded from disk).

    Shared by every plain plan of every dimension and model.
    """
    return numba.cfunc(_LOGP_SIGNATURE, cache=True)(_affine_logp)
