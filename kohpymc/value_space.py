r"""A PyMC model's unconstrained parameter space as one flat vector, compiled once.

Every sampler path of :func:`kohpymc.calibrate` starts here: the log density and its
gradient over PyMC's *value* variables (each free parameter after its default
transform: log for positive priors, logit-interval for bounded ones, identity for
unbounded) joined into one vector, and the map from that vector back to the user's
parameters and the model's deterministics.  Both are ordinary PyTensor functions,
compiled once per model (PyTensor's C backend keeps compiled code on disk, so a
rebuilt model of the same shape in a later process compiles from its cache).

:class:`ValueSpace` also knows, element by element, which transform PyMC used and the
bounds of interval priors, which :mod:`kohpymc.reparameterization` needs to offer a
log scale for positive bounded parameters.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import pymc as pm
import pytensor
import pytensor.tensor as pt
from pymc.distributions.transforms import Interval
from pymc.logprob.basic import transformed_conditional_logp
from pymc.logprob.transforms import IntervalTransform, LogTransform
from pymc.logprob.utils import replace_rvs_by_values
from pymc.pytensorf import constant_fold, join_nonshared_inputs

from kohpymc.batched_map import rows_function
from kohpymc.graph_cache import compile_cached
from kohpymc.physics.spec import singularity_offsets

__all__ = ["NumbaDensity", "ValueSpace", "transformed_value", "value_logp", "value_space"]


@dataclass(frozen=True)
class ValueSpace:
    """The flat unconstrained space of a model and its compiled functions.

    Attributes
    ----------
    names : tuple of str
        Value-variable names (``E_interval__``, ``sigma_obs_log__``, ...), in order.
    shapes : tuple of tuple
        Their shapes.
    initial : ndarray
        PyMC's initial point (support point of each prior), flattened.
    transforms : tuple of str
        Per flat element: ``"interval"``, ``"log"`` or ``"identity"``.
    lower, upper : ndarray
        Per flat element: interval bounds (NaN where not an interval transform).
    expanded_names, expanded_shapes :
        The user's parameters and deterministics that :attr:`expand` returns.
    """

    model: pm.Model
    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    initial: np.ndarray
    transforms: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    expanded_names: tuple[str, ...]
    expanded_shapes: tuple[tuple[int, ...], ...]
    _logp_dlogp: Callable[..., Any]
    _expand: Callable[..., Any]
    _expand_rows: Callable[..., Any] | None = None

    @property
    def ndim(self) -> int:
        """Length of the flat vector."""
        return int(self.initial.size)

    def logp_dlogp(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """Log density (with the transforms' Jacobians) and its gradient at ``x``."""
        logp, grad = self._logp_dlogp(np.asarray(x, dtype=float))
        return float(logp), np.asarray(grad, dtype=float)

    def logp_dlogp_or_nan(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """:meth:`logp_dlogp`, with ``(-inf, nan)`` where the model cannot be evaluated.

        For optimisers and finite differences, which may step far into the tails
        (e.g. where a physics function overflows and raises).
        """
        try:
            with np.errstate(all="ignore"):
                if isinstance(self._logp_dlogp, NumbaDensity):  # no compile to raise
                    result = self._logp_dlogp.evaluate(x)
                    if result is None:
                        return -np.inf, np.full(self.ndim, np.nan)
                    return float(result[0]), np.asarray(result[1], dtype=float)
                return self.logp_dlogp(x)
        except Exception:  # noqa: BLE001 - any failure is "outside the support" here
            return -np.inf, np.full(self.ndim, np.nan)

    def expand(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """The user's parameters and the model's deterministics at ``x``."""
        values = self._expand(np.asarray(x, dtype=float))
        return {
            name: np.asarray(value, dtype=float).reshape(shape)
            for name, value, shape in zip(
                self.expanded_names, values, self.expanded_shapes, strict=True
            )
        }

    def expand_rows(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`expand` of every row of ``rows`` (shape ``(n, ndim)``), stacked.

        One call of a map vectorised over the rows when the model allows it (see
        :func:`value_space`), else :meth:`expand` row by row.

        Examples
        --------
        >>> with pm.Model() as model:
        ...     s = pm.HalfNormal("s", 1.0)
        ...     _ = pm.Deterministic("s2", 2 * s)
        >>> space = value_space(model, mode="NUMBA")  # batched map: numpy, no compile
        >>> np.round(space.expand_rows(np.log([[1.0], [3.0]]))["s2"], 12).tolist()
        [2.0, 6.0]
        """
        rows = np.asarray(rows, dtype=float).reshape(-1, self.ndim)
        shapes = self.expanded_shapes
        if self._expand_rows is None:
            points = [self.expand(row) for row in rows]
            return {
                name: np.stack([p[name] for p in points]).reshape(len(rows), *shape)
                for name, shape in zip(self.expanded_names, shapes, strict=True)
            }
        values = self._expand_rows(rows)
        return {
            name: np.asarray(value, dtype=float).reshape(len(rows), *shape)
            for name, value, shape in zip(self.expanded_names, values, shapes, strict=True)
        }

    def split(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """``x`` as a point ``{value-variable name: array}`` (PyMC's point format)."""
        out, start = {}, 0
        for name, shape in zip(self.names, self.shapes, strict=True):
            size = int(np.prod(shape, dtype=int))
            out[name] = np.asarray(x[start : start + size]).reshape(shape)
            start += size
        return out

    def blocks(self) -> list[tuple[str, str, int, int]]:
        """``(variable name, value-variable name, first flat index, size)`` per free variable.

        Examples
        --------
        >>> import pymc as pm
        >>> with pm.Model() as model:
        ...     a = pm.HalfNormal("a", 1.0, shape=2)
        ...     b = pm.Normal("b")
        >>> value_space(model).blocks()
        [('a', 'a_log__', 0, 2), ('b', 'b', 2, 1)]
        """
        out, start = [], 0
        for rv, name, shape in zip(self.model.free_RVs, self.names, self.shapes, strict=True):
            size = int(np.prod(shape, dtype=int))
            out.append((rv.name, name, start, size))
            start += size
        return out

    def bounded_intervals(self) -> np.ndarray:
        """Mask of the flat elements sampled through an interval transform with finite bounds.

        Examples
        --------
        >>> import pymc as pm
        >>> with pm.Model() as model:
        ...     a = pm.Uniform("a", 0.0, 2.0)
        ...     b = pm.HalfNormal("b")
        >>> value_space(model).bounded_intervals().tolist()
        [True, False]
        """
        kinds = np.array(self.transforms)
        return (kinds == "interval") & np.isfinite(self.lower) & np.isfinite(self.upper)

    def join(self, point: dict[str, Any]) -> np.ndarray:
        """A point ``{value-variable name: array}`` as one flat vector."""
        return np.concatenate([np.ravel(np.asarray(point[name], float)) for name in self.names])


#: C signature of :attr:`NumbaDensity.c_function`: ``(x, theta, gradient out, logp out)``
#: -> 1, or 0 when the graph raised (numba's C wrapper then reports the exception to
#: :func:`sys.unraisablehook`, see :func:`quiet_density_errors`)
DENSITY_SIGNATURE = numba.types.int64(*[numba.types.CPointer(numba.types.double)] * 4)

#: the graph's numba function as a C function; ``theta`` holds the shared values (ARGS)
_DENSITY_TEMPLATE = """
def density_c(x_, theta_, out_, logp_):
    x = carray(x_, (N_DIM,))
    theta = carray(theta_, (N_THETA,))
    out = carray(out_, (N_DIM,))
    logp = carray(logp_, ())
    value, grad = graph(x, ARGS)
    logp[()] = value
    out[...] = grad
    return 1
"""

#: ``ctypes`` prototype of :data:`DENSITY_SIGNATURE` taking addresses
_DENSITY_CTYPE = ctypes.CFUNCTYPE(ctypes.c_int64, *[ctypes.c_void_p] * 4)


class NumbaDensity:
    """The log density and gradient of a NUMBA :class:`ValueSpace`: one numba C function.

    Calling it evaluates at a flat value vector, reading the graph's shared inputs at
    each call.  The graph is compiled once, into :attr:`c_function` (the graph inlined,
    cached on disk); :mod:`kohpymc.native` calls that same function from nutpie's
    density in the sampling coordinates (by its address, :meth:`theta`) instead of
    compiling the model's graph a second time.  When the graph cannot run as a C
    function (an Op numba runs in object mode) or raises, :attr:`call` (a numba
    function callable from Python, compiled at its first use) evaluates instead.

    Attributes
    ----------
    call : numba dispatcher
        ``call(x, *shared values)`` -> ``(logp, grad)``.
    shared : tuple
        The graph's shared variables, in argument order.
    key : str or None
        PyTensor's cache key of the graph (``None``: not cached on disk).
    """

    def __init__(
        self, call: Any, graph: Any, shared: tuple[Any, ...], key: str | None, ndim: int,
        python_ops: bool = False,
    ) -> None:  # fmt: skip
        self.call, self.shared, self.key = call, shared, key
        self._graph, self._ndim, self._python_ops = graph, ndim, python_ops
        self._compiled: tuple[Any, Any] | None = None
        self._tried = False
        self._theta_cache: tuple[tuple[Any, ...], np.ndarray] | None = None

    @property
    def c_function(self) -> Any:
        """The graph as a numba C function (:data:`DENSITY_SIGNATURE`), or None.

        Compiled (or loaded from numba's disk cache) at the first use; None when the
        graph holds an Op numba would run in object mode or the compile fails.
        """
        if not self._tried:
            self._tried = True
            self._compiled = self._compile_c()
        return None if self._compiled is None else self._compiled[0]

    def _compile_c(self) -> tuple[Any, Any] | None:
        """``(C function, its ctypes callable)``, or None (see :attr:`c_function`)."""
        from pytensor.link.numba.cache import compile_numba_function_src

        if self._python_ops:
            return None
        args = []
        start = 0
        for var in self.shared:
            value = np.asarray(var.get_value(borrow=True))
            part = f"theta[{start}:{start + value.size}].reshape({value.shape!r})"
            args.append(part if value.dtype == np.float64 else f"{part}.astype(np.{value.dtype})")
            start += value.size
        n = self._ndim
        env = {
            "N_DIM": n, "N_THETA": max(start, 1), "carray": numba.carray, "np": np,
            "graph": self._graph, "__name__": __name__,
        }  # fmt: skip
        source = _DENSITY_TEMPLATE.replace("ARGS", ", ".join(args))
        key = None
        if self.key is not None:
            values = [np.asarray(var.get_value()) for var in self.shared]
            layout = [(str(value.dtype), value.shape) for value in values]
            parts = f"{self.key}-{n}-{layout}".encode()
            key = f"kohpymc-density-c-v1-{hashlib.sha256(parts).hexdigest()}"
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("error", message="Numba will use object mode")
                raw = compile_numba_function_src(source, "density_c", env, cache_key=key)
                function = numba.cfunc(DENSITY_SIGNATURE, cache=key is not None)(raw)
        except Exception:  # noqa: BLE001 - the Python-callable function evaluates instead
            return None
        return function, _DENSITY_CTYPE(function.address)

    def theta(self) -> np.ndarray:
        """The shared values as :attr:`c_function` reads them (one float64 vector, ≥ 1 long).

        Joined again only when a shared variable holds another array than at the last
        call (``set_value`` stores a new one): an emulator's training data are ~1 MB, and
        joining them at every evaluation cost more than the evaluation (0.25 ms against
        ~0.05 ms in the mode search of the emulated dielectric calibration).  An array
        changed in place (PyTensor's ``borrow=True`` contract broken) is not noticed.
        """
        current = tuple(var.get_value(borrow=True) for var in self.shared)
        cached = self._theta_cache
        if cached is not None and all(a is b for a, b in zip(cached[0], current, strict=True)):
            return cached[1]
        values = [np.ravel(np.asarray(value, float)) for value in current]
        if not values or sum(v.size for v in values) == 0:
            joined = np.zeros(1)
        else:
            joined = np.ascontiguousarray(np.concatenate(values))
        self._theta_cache = (current, joined)
        return joined

    def __call__(self, x: np.ndarray) -> Any:
        """``(logp, grad)`` at the flat value vector ``x``; raises the graph's errors."""
        x = np.ascontiguousarray(x, dtype=float)
        result = self.evaluate(x)
        if result is None:  # the graph raised: its own error, from the Python-callable function
            return self._call_python(x)
        return result

    def evaluate(self, x: np.ndarray) -> tuple[Any, np.ndarray] | None:
        """``(logp, grad)`` at ``x``, or None when the graph raised in :attr:`c_function`.

        Without a C function, :attr:`call` evaluates (and raises).
        """
        x = np.ascontiguousarray(x, dtype=float)
        if self.c_function is None:
            return self._call_python(x)
        assert self._compiled is not None
        theta, grad, logp = self.theta(), np.empty(self._ndim), np.empty(())
        addresses = (x.ctypes.data, theta.ctypes.data, grad.ctypes.data, logp.ctypes.data)
        with quiet_density_errors():
            ok = self._compiled[1](*addresses)
        return (logp[()], grad) if ok == 1 else None

    def _call_python(self, x: np.ndarray) -> Any:
        values = [var.get_value(borrow=True) for var in self.shared]
        return self.call(x, *values)


def _is_density_error(record: Any) -> bool:
    """Whether an unraisable record is numba's C wrapper reporting a graph's exception."""
    return str(getattr(record, "object", "")).startswith("<numba.core.cpu.CPUContext")


@contextlib.contextmanager
def quiet_density_errors():
    """Leave out numba's report of exceptions inside :data:`DENSITY_SIGNATURE` functions.

    A graph that raises inside a numba C function (e.g. a Cholesky factor of a matrix
    that is not positive definite, far in a posterior's tails) returns 0, and numba's C
    wrapper hands the exception to :func:`sys.unraisablehook`, which prints it; the
    callers treat that evaluation as failed instead.  Other unraisable records go to the
    hook as before.
    """
    previous = sys.unraisablehook

    def hook(record: Any) -> None:
        if not _is_density_error(record):
            previous(record)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _direct_numba_call(function: Any, ndim: int) -> Callable[..., Any]:
    """``function`` (NUMBA mode) as one numba function around the graph's, cached on disk.

    PyTensor calls its graph's numba function through two wrappers, and numba generates
    the machine code of everything a function calls once per function, so each wrapper
    level is one more code generation of the whole graph from an empty cache; here the
    graph is inlined into the one function Python calls (a :class:`NumbaDensity`).  The
    function's shared inputs (e.g. data) are read at each call.  ``function`` itself
    when its numba function is not structured as PyTensor's.
    """
    from pytensor.link.numba.cache import CACHED_SRC_FUNCTIONS, compile_numba_function_src
    from pytensor.link.numba.dispatch.basic import numba_njit

    from kohpymc.native import python_only_ops

    jit_fn = getattr(getattr(function, "vm", None), "jit_fn", None)
    wrapper: Any = getattr(jit_fn, "py_func", None)
    graph = getattr(wrapper, "__globals__", {}).get("jitable_func")
    if graph is None or getattr(graph, "py_func", None) is None:
        return function
    shared = tuple(spec.variable for spec in function.maker.inputs[1:])
    graph_key = CACHED_SRC_FUNCTIONS.get(wrapper)
    names = ", ".join(f"x{i}" for i in range(1 + len(shared)))
    key = None if graph_key is None else f"kohpymc-value-logp-v1-{graph_key}-{len(shared)}"
    inlined = numba_njit(graph.py_func, inline="always")
    env = {"graph": inlined, "__name__": __name__}
    source = f"def value_logp({names}):\n    return graph({names})\n"
    raw = compile_numba_function_src(source, "value_logp", env, cache_key=key)
    call = numba_njit(raw, final_function=True, cache=key is not None)
    python_ops = bool(python_only_ops(function.maker.fgraph.outputs))
    return NumbaDensity(call, inlined, shared, graph_key, ndim, python_ops)


def _constant_value(bound: Any) -> np.ndarray:
    """A prior bound's numeric value, by constant folding (no compiled function).

    Raises when the bound depends on a model variable.
    """
    folded = constant_fold([pt.as_tensor(bound)], raise_not_constant=True)[0]
    return np.asarray(getattr(folded, "data", folded), dtype=float)


def _finite_bounds(transform: Any, rv: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """An interval transform's bounds as numbers, or None when not constant and finite."""
    a, b, _, _ = transform.get_a_and_b(rv.owner.inputs)
    try:
        lower, upper = _constant_value(a), _constant_value(b)
    except Exception:  # noqa: BLE001 - bounds that depend on other parameters
        return None
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
        return None
    return lower, upper


def transformed_value(model: pm.Model, rv: Any, values: Any) -> np.ndarray:
    """``values`` of the free variable ``rv`` in its value space (PyMC's transform applied).

    PyMC's log and interval (constant finite bounds) transforms are computed in numpy
    (``log v`` and ``log(v - a) - log(b - v)``, PyMC's formulas); any other is evaluated in
    PyTensor's Python mode (each evaluation compiles a small graph, ~70 ms; the default C
    backend's first compile in a process reads its whole module cache, 3–5 s on a
    well-used machine).

    Examples
    --------
    >>> import pymc as pm
    >>> with pm.Model() as model:
    ...     s = pm.HalfNormal("s", 1.0)
    >>> transformed_value(model, s, [1.0, np.e])
    array([0., 1.])
    """
    values = np.asarray(values, dtype=float)
    transform = model.rvs_to_transforms.get(rv)
    if transform is None:
        return values
    if isinstance(transform, LogTransform):
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(values)
    if isinstance(transform, IntervalTransform):
        bounds = _finite_bounds(transform, rv)
        if bounds is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.log(values - bounds[0]) - np.log(bounds[1] - values)
    forward = transform.forward(values, *rv.owner.inputs)
    return np.asarray(forward.eval(mode="FAST_COMPILE"), dtype=float)


def _transform_info(model: pm.Model, rv: Any, size: int) -> tuple[str, np.ndarray, np.ndarray]:
    """Transform kind and (for intervals) numeric bounds of one free variable."""
    transform = model.rvs_to_transforms.get(rv)
    nan = np.full(size, np.nan)
    if transform is None:
        return "identity", nan, nan
    if isinstance(transform, LogTransform):
        return "log", nan, nan
    if isinstance(transform, IntervalTransform):
        a, b, _, _ = transform.get_a_and_b(rv.owner.inputs)
        try:
            lower = np.broadcast_to(_constant_value(a), size).copy()
            upper = np.broadcast_to(_constant_value(b), size).copy()
        except Exception:  # noqa: BLE001 - bounds that depend on other parameters
            return "other", nan, nan
        return "interval", lower, upper
    return "other", nan, nan


class _FiniteInterval(IntervalTransform):
    """PyMC's interval transform for constant finite bounds, without its infinite-bound cases.

    PyMC's :class:`~pymc.logprob.transforms.IntervalTransform` builds every map with
    switches for infinite bounds (``a ≠ -inf``, ``b ≠ inf``), ~20 nodes per parameter that
    PyTensor rewrites away at every compile; with numbers for bounds these are PyMC's
    formulas of the finite case: ``θ = σ(x) b + (1 - σ(x)) a`` and ``log|dθ/dx| =
    log(b - a) - 2 softplus(-x) - x``.
    """

    def __init__(self, lower: np.ndarray, upper: np.ndarray) -> None:
        super().__init__(lambda *inputs: (pt.as_tensor(lower), pt.as_tensor(upper)))
        self.lower, self.upper = lower, upper

    def forward(self, value: Any, *inputs: Any) -> Any:
        return pt.log(value - self.lower) - pt.log(self.upper - value)

    def backward(self, value: Any, *inputs: Any) -> Any:
        sigmoid_x = pt.sigmoid(value)
        return sigmoid_x * self.upper + (1 - sigmoid_x) * self.lower

    def log_jac_det(self, value: Any, *inputs: Any) -> Any:
        return np.log(self.upper - self.lower) - 2 * pt.softplus(-value) - value


def _lean_uniform(model: pm.Model, rv: Any) -> _FiniteInterval | None:
    """The lean transform of a free Uniform prior with PyMC's interval transform, or None.

    None unless the prior's bounds and its transform's are the same constant finite
    numbers.
    """
    transform = model.rvs_to_transforms.get(rv)
    if not isinstance(rv.owner.op, pm.Uniform.rv_type) or type(transform) is not Interval:
        return None
    bounds = _finite_bounds(transform, rv)
    if bounds is None:
        return None
    try:
        own = [_constant_value(bound) for bound in rv.owner.inputs[-2:]]
    except Exception:  # noqa: BLE001 - the prior's own bounds depend on other parameters
        return None
    lower, upper, rv_lower, rv_upper = np.broadcast_arrays(*bounds, *own)
    if not (np.all(lower < upper) and np.array_equal(lower, rv_lower)):
        return None
    if not np.array_equal(upper, rv_upper):
        return None
    return _FiniteInterval(bounds[0], bounds[1])


def value_logp(model: pm.Model) -> Any:
    """``model.logp()`` (with the transforms' Jacobians) as a leaner graph.

    Every free Uniform prior with PyMC's interval transform and constant finite bounds
    enters through :class:`_FiniteInterval` (θ wherever the model uses it, and its
    Jacobian), and its own term — the prior's ``-log(b - a)`` plus the Jacobian — is
    ``-2 softplus(-x) - x``, exactly (``θ`` is inside ``[a, b]`` for every ``x``; PyMC's
    graph checks it).  On the emulated dielectric model (seven Uniform priors) the log
    density has ~190 nodes instead of 631.

    Examples
    --------
    >>> with pm.Model() as model:
    ...     theta = pm.Uniform("theta", 1.0, 3.0)
    ...     _ = pm.Normal("y", theta, 1.0, observed=[2.5])
    >>> point = {"theta_interval__": np.array(0.4)}
    >>> lean = value_logp(model).eval(point)
    >>> bool(np.isclose(lean, model.logp().eval(point)))
    True
    """
    lean = {rv: _lean_uniform(model, rv) for rv in model.free_RVs}
    lean = {rv: transform for rv, transform in lean.items() if transform is not None}
    transforms = {**model.rvs_to_transforms, **lean}
    rvs = model.free_RVs + model.observed_RVs
    terms = transformed_conditional_logp(
        rvs, rvs_to_values=model.rvs_to_values, rvs_to_transforms=transforms
    )
    terms += replace_rvs_by_values(
        model.potentials, rvs_to_values=model.rvs_to_values, rvs_to_transforms=transforms
    )
    out = []
    for rv, term in zip(rvs, terms[: len(rvs)], strict=True):
        if rv in lean:
            x = model.rvs_to_values[rv]
            term = -2 * pt.softplus(-x) - x
        out.append(pt.sum(term))
    out += [pt.sum(term) for term in terms[len(rvs) :]]
    logp = pt.add(*out) if out else pt.constant(0.0)
    logp.name = "__logp"
    return logp


def _expand_mode(mode: str | None, graphs: Sequence[Any] = ()) -> str | None:
    """Compile mode of the expand map ``graphs`` when the log density's is ``mode``.

    The expand map runs once per kept draw (~50 µs either way on the beam), so its compile
    time is what counts.  With a Python Op in it (a numpy physics function) numba compiles
    it at its first call and cannot cache it across processes (1–3 s per beam
    formulation), while the C backend finds its modules in PyTensor's on-disk cache: the
    C backend then, when a C compiler is available.  A pure PyTensor map stays with
    NUMBA, which caches it on disk: the C backend's first compile in a process reads its
    whole module cache (3–5 s with the ~1,200 modules of a well-used cache), which the
    emulated dielectric calibration paid for a map of 14 nodes.  Without a C compiler the
    map stays with NUMBA (PyTensor's Python fallback would cost milliseconds per draw).

    Examples
    --------
    >>> _expand_mode("FAST_RUN")
    'FAST_RUN'
    >>> import pytensor.tensor as pt
    >>> _expand_mode("NUMBA", [pt.exp(pt.vector("x"))])
    'NUMBA'
    """
    from kohpymc.native import python_only_ops

    if mode != "NUMBA" or not pytensor.config.cxx:
        return mode
    if graphs and not python_only_ops(graphs):
        return "NUMBA"
    return "FAST_RUN"


def value_space(model: pm.Model, *, mode: str | None = None) -> ValueSpace:
    """Compile the flat log density, its gradient and the expand map of ``model``.

    Parameters
    ----------
    model : pymc.Model
        A model whose free variables are all continuous.
    mode : str, optional
        PyTensor compile mode of the log density and gradient (default: PyTensor's
        default, the C backend).  With ``"NUMBA"`` an expand map holding a Python Op
        is compiled by the C backend when a C compiler is available (:func:`_expand_mode`).

    Returns
    -------
    ValueSpace

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> with pm.Model() as model:
    ...     mu = pm.Normal("mu", 0.0, 10.0)
    ...     _ = pm.Normal("y", mu, 1.0, observed=[1.0, 2.0])
    >>> space = value_space(model)
    >>> logp, grad = space.logp_dlogp(np.array([1.5]))
    >>> float(np.round(grad[0], 4))  # d/dmu: (1 - 1.5) + (2 - 1.5) - 1.5 / 100
    -0.015
    """
    discrete = [rv.name for rv in model.free_RVs if not str(rv.dtype).startswith("float")]
    if discrete:
        raise ValueError(f"gradient samplers need continuous parameters; discrete: {discrete}")
    point = model.initial_point(0)
    value_vars = list(model.value_vars)
    names = tuple(v.name for v in value_vars)
    shapes = tuple(tuple(np.shape(point[n])) for n in names)
    kinds: list[str] = []
    lower, upper = [], []
    for rv, shape in zip(model.free_RVs, shapes, strict=True):
        size = int(np.prod(shape, dtype=int))
        kind, a, b = _transform_info(model, rv, size)
        kinds.extend([kind] * size)
        lower.append(a)
        upper.append(b)
    logp = value_logp(model)
    grads = pytensor.grad(logp, value_vars, disconnected_inputs="ignore")
    outputs = [logp, pt.join(0, *[pt.as_tensor(g).ravel() for g in grads])]  # type: ignore[union-attr]
    joined_outputs, flat = join_nonshared_inputs(
        point=point, outputs=outputs, inputs=value_vars, make_inputs_shared=False
    )
    with warnings.catch_warnings():
        # numba runs a numpy-function physics Op in object mode: correct, only slower
        warnings.filterwarnings("ignore", message="Numba will use object mode")
        if mode == "NUMBA":  # its rewrites kept on disk (the C backend caches its own code)
            logp_dlogp = compile_cached([flat], joined_outputs, mode=mode)
        else:
            logp_dlogp = pm.pytensorf.compile([flat], joined_outputs, mode=mode)
    if mode == "NUMBA":
        logp_dlogp = _direct_numba_call(logp_dlogp, sum(int(np.prod(s, dtype=int)) for s in shapes))
    expanded = list(model.free_RVs) + list(model.deterministics)
    expanded_graphs = model.replace_rvs_by_values(expanded)
    expand_outputs, flat_e = join_nonshared_inputs(
        point=point, outputs=expanded_graphs, inputs=value_vars, make_inputs_shared=False
    )
    initial = np.concatenate([np.ravel(point[n]) for n in names]).astype(float)
    rows_map = rows_function(flat_e, expand_outputs) if mode == "NUMBA" else None
    if rows_map is not None:
        expand = functools.partial(_first_row, rows_map)
    else:
        expand_mode = _expand_mode(mode, expand_outputs)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Numba will use object mode")
            expand = pm.pytensorf.compile(
                [flat_e], expand_outputs, on_unused_input="ignore",
                **({} if expand_mode is None else {"mode": expand_mode}),
            )  # fmt: skip
    expanded_shapes = tuple(tuple(np.shape(v)) for v in _expand_near(expand, initial))
    return ValueSpace(
        model=model,
        names=names,
        shapes=shapes,
        initial=initial,
        transforms=tuple(kinds),
        lower=np.concatenate(lower) if lower else np.zeros(0),
        upper=np.concatenate(upper) if upper else np.zeros(0),
        expanded_names=tuple(v.name for v in expanded),
        expanded_shapes=expanded_shapes,
        _logp_dlogp=logp_dlogp,
        _expand=expand,
        _expand_rows=rows_map,
    )


def nudged(initial: np.ndarray) -> Iterator[np.ndarray]:
    """``initial``, then points next to it where equal elements part.

    The initial point (each prior's centre) can be a removable singularity of a correct
    model: ``ka / (ka - ke)`` when ``ka`` and ``ke`` have the same prior.  Each element
    moves by :func:`~kohpymc.physics.spec.singularity_offsets`.

    Examples
    --------
    >>> [p.round(4).tolist() for p in nudged(np.zeros(2))][:2]
    [[0.0, 0.0], [0.0005, -0.001]]
    """
    initial = np.asarray(initial, dtype=float)
    yield initial
    for offsets in singularity_offsets(initial.size):
        yield initial + offsets


def _expand_near(expand: Callable[..., Any], initial: np.ndarray) -> list[Any]:
    """``expand`` at the initial point, or next to it when the model fails there."""
    error: Exception | None = None
    for point in nudged(initial):
        try:
            with np.errstate(all="ignore"):
                return list(expand(point))
        except Exception as err:  # noqa: BLE001 - the first error is raised if none runs
            error = error or err
    assert error is not None
    raise error


def _first_row(rows_map: Callable[..., Any], x: np.ndarray) -> list[np.ndarray]:
    """``rows_map`` of the single flat vector ``x``."""
    return [value[0] for value in rows_map(np.asarray(x)[None])]
