"""A PyTensor graph of one flat vector evaluated for many vectors at once, without a compile.

The map from PyMC's value space to the user's parameters and deterministics runs once
per kept draw.  Compiled by numba it costs nothing per draw, but from an empty cache its
compile takes 2–12 s per beam formulation (12 s for the GP formulation M4, whose map
holds a Cholesky factor and triangular solves).  Here the graph is vectorised over rows
(:func:`pytensor.graph.replace.vectorize_graph`) and run by PyTensor's Python linker:
one numpy call per node for all draws.  The batched linear algebra that PyTensor's
Python linker would run one row at a time (``Blockwise`` of ``Cholesky``,
``CholeskySolve``, ``SolveTriangular``) is replaced by numpy's stacked routines.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytensor.tensor as pt
from pytensor.graph.basic import Apply
from pytensor.graph.op import Op
from pytensor.graph.rewriting.basic import node_rewriter
from pytensor.tensor.blockwise import Blockwise
from pytensor.tensor.elemwise import Elemwise

__all__ = ["rows_function"]


def _stacked_cholesky(op: Any, a: np.ndarray) -> np.ndarray:
    """``Cholesky`` of every matrix in ``a`` (NaN where one is not positive definite)."""
    try:
        factor = np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        factor = np.full(a.shape, np.nan)
        for index in np.ndindex(a.shape[:-2]):
            try:
                factor[index] = np.linalg.cholesky(a[index])
            except np.linalg.LinAlgError:
                pass
    return factor if op.lower else np.swapaxes(factor, -1, -2)


def _triangle(a: np.ndarray, lower: bool) -> np.ndarray:
    """The lower or upper triangle of every matrix in ``a`` (LAPACK reads only that)."""
    return np.tril(a) if lower else np.triu(a)


def _solve(a: np.ndarray, b: np.ndarray, b_ndim: int) -> np.ndarray:
    """``a⁻¹ b`` for stacks of matrices ``a`` and vectors (``b_ndim`` 1) or matrices ``b``."""
    if b_ndim == 1:
        return np.linalg.solve(a, b[..., None])[..., 0]
    return np.linalg.solve(a, b)


def _stacked_cholesky_solve(op: Any, c: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``CholeskySolve``: ``(C Cᵀ)⁻¹ b`` for a lower factor ``C`` (``(Cᵀ C)⁻¹ b`` upper)."""
    c = _triangle(c, op.lower)
    ct = np.swapaxes(c, -1, -2)
    first, second = (c, ct) if op.lower else (ct, c)
    return _solve(second, _solve(first, b, op.b_ndim), op.b_ndim)


def _stacked_solve_triangular(op: Any, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``SolveTriangular``: ``a⁻¹ b`` reading only ``a``'s triangle."""
    a = _triangle(a, op.lower)
    if op.unit_diagonal:
        a = a.copy()
        np.einsum("...ii->...i", a)[...] = 1.0
    return _solve(a, b, op.b_ndim)


_STACKED: dict[str, Callable[..., np.ndarray]] = {
    "Cholesky": _stacked_cholesky,
    "CholeskySolve": _stacked_cholesky_solve,
    "SolveTriangular": _stacked_solve_triangular,
}


class _Stacked(Op):
    """A ``Blockwise`` linear-algebra node computed by numpy's stacked routines."""

    __props__ = ("core_op",)

    def __init__(self, core_op: Op) -> None:
        self.core_op = core_op

    def make_node(self, *inputs: Any) -> Apply:  # the Blockwise node's output type
        raise NotImplementedError("built from a Blockwise node by _stacked_linalg")

    def perform(self, node: Apply, inputs: Sequence[Any], outputs: Any) -> None:
        result = _STACKED[type(self.core_op).__name__](self.core_op, *inputs)
        outputs[0][0] = np.asarray(result, dtype=node.outputs[0].type.dtype)


@node_rewriter([Blockwise])
def _stacked_linalg(fgraph: Any, node: Apply) -> list[Any] | None:
    """A Blockwise linear-algebra node as :class:`_Stacked` (numpy's stacked routines)."""
    core = node.op.core_op
    if type(core).__name__ not in _STACKED or len(node.outputs) != 1:
        return None
    if type(core).__name__ == "Cholesky" and getattr(core, "on_error", "nan") == "raise":
        return None
    return [Apply(_Stacked(core), list(node.inputs), [node.outputs[0].type()]).outputs[0]]


@node_rewriter([Elemwise])
def _numpy_elemwise(fgraph: Any, node: Apply) -> list[Any] | None:
    """An Elemwise that the Python linker would run per element, as numpy ufuncs.

    PyTensor's rewrites join sums and products of more than two terms into one node, and
    numpy has no ufunc for those (nor for ``Clip``): the Python linker then calls the
    scalar operation once per element (1.6 million Python calls for the beam GP's 4,000
    draws).  Here they become chains of two-term ufuncs (``Clip`` two ``where``).
    """
    from pytensor.scalar import Add, Clip, Mul

    scalar = node.op.scalar_op
    inputs = node.inputs
    if isinstance(scalar, Add | Mul) and len(inputs) > 2:
        combine = pt.add if isinstance(scalar, Add) else pt.mul
        out = combine(inputs[0], inputs[1])
        for term in inputs[2:]:
            out = combine(out, term)
    elif isinstance(scalar, Clip):
        x, low, high = inputs
        out = pt.switch(pt.lt(x, low), low, pt.switch(pt.gt(x, high), high, x))
    else:
        return None
    return [pt.cast(out, node.outputs[0].type.dtype)]


def rows_function(
    flat: Any, outputs: Sequence[Any], optimizer: str = "fast_run"
) -> Callable[..., list[np.ndarray]] | None:
    """``outputs`` (graphs of the vector ``flat``) as a function of a matrix of rows.

    ``optimizer``: PyTensor's rewrites of the batched graph (``"None"``: none, for a
    function evaluated once, where rewriting costs more than it saves).

    Returns
    -------
    callable or None
        ``f(rows)`` -> one array per output with a leading axis of the rows (an output
        that does not depend on ``flat`` repeated), or ``None`` when the graph cannot be
        vectorised or a node would still run once per row in Python.

    Examples
    --------
    >>> x = pt.vector("x")
    >>> f = rows_function(x, [pt.exp(x[0]) + x[1]])
    >>> f(np.array([[0.0, 1.0], [0.0, 2.0]]))[0].tolist()
    [2.0, 3.0]
    """
    from pytensor.compile.mode import Mode
    from pytensor.graph.replace import vectorize_graph
    from pytensor.graph.rewriting.basic import in2out

    from kohpymc.graph_cache import compile_cached

    if _slow_to_vectorize(outputs):
        return None
    rows = pt.matrix("rows")
    try:
        batched = vectorize_graph(list(outputs), {flat: rows})
    except NotImplementedError:
        return None
    numpy_calls = (in2out(_numpy_elemwise, _stacked_linalg, name="kohpymc_numpy_calls"), 49.2)
    mode = Mode(linker="py", optimizer=optimizer).excluding("fusion").register(numpy_calls)
    function = compile_cached(
        [rows], batched, mode=mode, label=f"kohpymc-rows-{optimizer}", on_unused_input="ignore"
    )
    if any(_per_row(node.op) for node in function.maker.fgraph.apply_nodes):
        return None
    per_row = [b.type.ndim > o.type.ndim for b, o in zip(batched, outputs, strict=True)]

    def evaluate(x: np.ndarray) -> list[np.ndarray]:
        """Every output with a leading axis of the rows of ``x``."""
        values = function(x)
        return [
            np.asarray(v) if along else np.broadcast_to(v, (len(x), *np.shape(v)))
            for v, along in zip(values, per_row, strict=True)
        ]

    return evaluate


def _slow_to_vectorize(outputs: Sequence[Any]) -> bool:
    """Whether the graph has more ``Shape`` nodes than vectorising can afford.

    PyTensor vectorises a ``Shape`` node through ``broadcast_to`` and re-infers static
    shapes each time, rewriting the shape graph: a GridGP calibration's expand map, with
    25 ``Shape`` nodes over a Kronecker structure, took 598 s to vectorise, against 44 s
    for the whole calibration before (the compiled per-draw map is used instead).
    """
    from pytensor.graph.traversal import ancestors
    from pytensor.tensor.shape import Shape, Shape_i

    shapes = sum(
        1
        for v in ancestors(outputs)
        if v.owner is not None and isinstance(v.owner.op, Shape | Shape_i)
    )
    return shapes > _MAX_SHAPES


#: ``Shape`` nodes above which a graph is not vectorised (see :func:`_slow_to_vectorize`):
#: the beam's and a dense GP's expand maps have none, GridGP's 25
_MAX_SHAPES = 4


def _per_row(op: Any) -> bool:
    """Whether the Python linker runs ``op`` row by row (a Blockwise without gufunc)."""
    from pytensor.compile.ops import ViewOp

    if not isinstance(op, Blockwise):
        return False
    return (
        op.gufunc_spec is None
        and getattr(op.core_op, "gufunc_spec", None) is None
        and not isinstance(op.core_op, ViewOp)
    )
