"""Rewritten PyTensor graphs kept on disk, so that a later process links instead of rewriting.

Compiling a log density and its gradient in PyTensor's NUMBA mode is two steps: the
graph rewrites (canonicalisation, specialisation, fusion, in-place), then numba's code
generation, which numba already caches on disk.  The rewrites are done again in every
process: ~1.3 CPU-s of the 1.6 s that an emulated dielectric calibration spent compiling
its log density.  :func:`compile_cached` keeps the rewritten graph, keyed by the graph it
was given; a later compile of the same graph unpickles it and only links (~0.3 s there).

The key (:func:`graph_key`) is a hash of the graph's structure: every node's Op by its
class and ``__props__`` (the same equality PyTensor's merge rewrite relies on), the
types of the inputs and shared variables, the constants' values, and the versions of
Python, PyTensor, PyMC, numba and kohpymc's own source.  Shared variables (data) are
not in it: the cached graph holds placeholders that the caller's shared variables
replace, so ``pm.set_data`` works as on a freshly compiled function.  An ``OpFromGraph``
(``pt.diag``'s ``AllocDiag``, ...) is keyed by its inner graph.  A graph is compiled the
usual way, and not cached, when some Op cannot be keyed (no ``__props__``, or a value
without a stable description), when it runs Python code of the user's (a numpy physics
Op: its source may change under the same name), or when it draws random
numbers.  A cache file that cannot be read is compiled again and rewritten.

``KOHPYMC_GRAPH_CACHE=0`` turns the cache off; files are in
``<pytensor compiledir>/kohpymc-graphs`` (each Dask worker has its own compiledir).
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import pickle
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytensor
from pytensor.compile.builders import OpFromGraph
from pytensor.compile.mode import Mode
from pytensor.compile.sharedvalue import SharedVariable
from pytensor.graph.basic import Constant, Variable
from pytensor.graph.op import Op
from pytensor.graph.replace import clone_replace
from pytensor.graph.traversal import graph_inputs, io_toposort
from pytensor.graph.type import Type

__all__ = ["compile_cached", "graph_key"]

_log = logging.getLogger(__name__)

#: bumped when the payload's layout changes
_FORMAT = 1

#: most files kept; the least recently used beyond this are removed when one is written
_KEEP = 300

#: PyTensor's named modes that are cached (a ``Mode`` object with a ``label`` also is)
_CACHED_MODES = ("NUMBA", "FAST_RUN")


class _Unkeyable(Exception):
    """A part of the graph has no stable description."""


def compile_cached(
    inputs: Sequence[Variable],
    outputs: Sequence[Variable],
    *,
    mode: str | Mode,
    label: str | None = None,
    **kwargs: Any,
) -> Any:
    """``pm.pytensorf.compile(inputs, outputs, mode=mode, **kwargs)``, its rewrites cached.

    Parameters
    ----------
    inputs, outputs : sequences of Variable
        As for :func:`pymc.pytensorf.compile`; shared variables are implicit inputs.
    mode : str or Mode
        The compile mode.  ``"NUMBA"`` and ``"FAST_RUN"`` are cached; a ``Mode`` object
        only with a ``label`` that names its rewrites (they are not in the key); other
        modes are compiled without the cache.
    label : str, optional
        With a ``Mode`` object: a name of its rewrites, changed whenever they change.
    **kwargs
        Passed on (``on_unused_input``, ...).

    Returns
    -------
    pytensor.compile.function.types.Function

    Examples
    --------
    >>> import numpy as np, pytensor.tensor as pt
    >>> x = pt.vector("x")
    >>> f = compile_cached([x], [pt.exp(x).sum()], mode="NUMBA")
    >>> float(f(np.zeros(3))[0])
    3.0
    """
    import pymc as pm

    if isinstance(mode, str):
        name = mode if mode in _CACHED_MODES else None
    else:
        name = label
    key = None if name is None else _key_or_none(inputs, outputs, name)
    if key is None:
        return pm.pytensorf.compile(list(inputs), list(outputs), mode=mode, **kwargs)
    path = _directory() / f"{key}.pkl"
    function = _load(path, inputs, outputs, _linker(mode), kwargs)
    if function is None:
        function = _rewrite_store_link(path, inputs, outputs, mode, kwargs)
    if function is None:
        function = pm.pytensorf.compile(list(inputs), list(outputs), mode=mode, **kwargs)
    return function


def _rewrite_store_link(
    path: Path, inputs: Sequence[Variable], outputs: Sequence[Variable], mode: str | Mode,
    kwargs: dict[str, Any],
) -> Any:  # fmt: skip
    """A graph not yet cached: rewritten, written to ``path``, linked from it (or None).

    Rewritten with Python thunks (nothing compiled), then linked from the file as later
    processes will be: numba's source (so its disk cache key) of a linked graph differs
    from that of the graph it was rewritten from, and numba would compile both.
    """
    import pymc as pm

    try:
        rewritten = pm.pytensorf.compile(
            list(inputs), list(outputs), mode=_rewriting(mode), **kwargs
        )
    except Exception as err:  # noqa: BLE001 - the usual compile then raises the model's error
        _log.debug("graph not rewritten alone: %s", err)
        return None
    _store(path, rewritten, len(inputs), _shared(outputs))
    return _load(path, inputs, outputs, _linker(mode), kwargs)


def graph_key(inputs: Sequence[Variable], outputs: Sequence[Variable], mode: str) -> str:
    """A hash of everything the rewritten graph of ``outputs`` depends on.

    Raises
    ------
    ValueError
        When some Op or constant has no stable description.

    Examples
    --------
    >>> import pytensor.tensor as pt
    >>> x = pt.vector("x")
    >>> graph_key([x], [x + 1.0], "NUMBA") == graph_key([x], [x + 1.0], "NUMBA")
    True
    >>> graph_key([x], [x + 1.0], "NUMBA") == graph_key([x], [x + 2.0], "NUMBA")
    False
    """
    try:
        parts = [f"mode {mode}", *_graph_lines(inputs, outputs)]
    except _Unkeyable as err:
        raise ValueError(f"the graph cannot be keyed: {err}") from None
    digest = hashlib.sha256(_versions().encode())
    for line in parts:
        digest.update(line.encode())
        digest.update(b"\n")
    return digest.hexdigest()


def _key_or_none(inputs: Sequence[Variable], outputs: Sequence[Variable], mode: str) -> str | None:
    """The cache key, or None when this graph is compiled without the cache."""
    from kohpymc.native import python_only_ops

    if os.environ.get("KOHPYMC_GRAPH_CACHE") == "0":
        return None
    if python_only_ops(outputs) or _draws_random_numbers(outputs):
        return None
    try:
        return graph_key(inputs, outputs, mode)
    except ValueError as err:
        _log.debug("compiled without the graph cache: %s", err)
        return None


def _graph_lines(inputs: Sequence[Variable], outputs: Sequence[Variable]) -> list[str]:
    """One line per input, shared variable, constant and node, with canonical names."""
    names: dict[Variable, str] = {}
    lines = []
    for i, variable in enumerate(inputs):
        names[variable] = f"i{i}"
        lines.append(f"input {i} {variable.type}")
    for k, variable in enumerate(_shared(outputs)):
        names[variable] = f"s{k}"
        lines.append(f"shared {k} {variable.type}")
    for node in io_toposort(list(inputs), list(outputs)):
        for variable in node.inputs:
            if variable not in names:
                names[variable] = _root_name(variable, len(names), lines)
        arguments = ",".join(names[v] for v in node.inputs)
        lines.append(f"{_op_key(node.op)}({arguments})")
        for output in node.outputs:
            names[output] = f"v{len(names)}"
    for variable in outputs:
        if variable not in names:
            names[variable] = _root_name(variable, len(names), lines)
    lines.append("outputs " + ",".join(names[v] for v in outputs))
    return lines


def _root_name(variable: Variable, number: int, lines: list[str]) -> str:
    """A constant's canonical name (its line added); any other root cannot be keyed."""
    if not isinstance(variable, Constant):
        raise _Unkeyable(f"a free variable {variable} that is not an input")
    lines.append(f"constant c{number} {variable.type} {_describe(variable.data)}")
    return f"c{number}"


def _op_key(op: Op) -> str:
    """An Op's class and properties."""
    from pytensor.scalar.basic import Composite, ScalarOp

    cls = type(op)
    name = f"{cls.__module__}.{cls.__qualname__}"
    if isinstance(op, OpFromGraph):
        return name + _inner_graph_key(op)
    props = getattr(cls, "__props__", None)
    if props is not None:  # what PyTensor's merge rewrite compares
        return name + _describe(tuple(getattr(op, prop) for prop in props))
    if isinstance(op, ScalarOp) and not isinstance(op, Composite):
        return name + _describe((op.name, op.output_types_preference))
    raise _Unkeyable(f"Op {name} has no __props__")


def _inner_graph_key(op: OpFromGraph) -> str:
    """An OpFromGraph (``pt.diag``'s ``AllocDiag``, ...): its settings and inner graph.

    Its behaviour is its inner graph; the plain settings of the subclass (``offset``,
    ``axis1``, ...) are in the key too, as rewrites may read them.  Gradient overrides
    and shared inputs are not described, so such an Op is not keyed.
    """
    overrides = (op.lop_overrides, op.grad_overrides, op.rop_overrides)
    if op.shared_inputs or any(o is not None for o in overrides):
        raise _Unkeyable(f"Op {type(op).__qualname__} has shared inputs or overrides")
    settings = {
        k: v for k, v in vars(op).items()
        if not k.startswith("_") and isinstance(v, bool | int | float | str)
    }  # fmt: skip
    inner = _graph_lines(op.inner_inputs, op.inner_outputs)
    return _describe(settings) + "[" + ";".join(inner) + "]"


def _describe(value: Any) -> str:
    """A description of an Op property or constant that is equal iff the values are."""
    if value is None or isinstance(value, bool | int | float | complex | str | bytes):
        return repr(value)
    if isinstance(value, np.ndarray):
        data = hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()
        return f"array({value.dtype},{value.shape},{data})"
    if isinstance(value, np.generic):
        return f"{value.dtype}({value.item()!r})"
    if isinstance(value, tuple | list):
        return "(" + ",".join(_describe(v) for v in value) + ")"
    if isinstance(value, Mapping):
        items = sorted((_describe(k), _describe(v)) for k, v in value.items())
        return "{" + ",".join(f"{k}:{v}" for k, v in items) + "}"
    if isinstance(value, Op):
        return _op_key(value)
    if isinstance(value, Type | slice):
        return repr(value)
    if callable(value) and hasattr(value, "__qualname__"):
        return f"{getattr(value, '__module__', '')}.{value.__qualname__}"
    text = repr(value)
    if " at 0x" in text:
        raise _Unkeyable(f"no stable description of {text}")
    return f"{type(value).__qualname__}:{text}"


def _shared(outputs: Sequence[Variable]) -> list[SharedVariable]:
    """The shared variables ``outputs`` depend on, in graph order."""
    return [v for v in graph_inputs(list(outputs)) if isinstance(v, SharedVariable)]


def _draws_random_numbers(outputs: Sequence[Variable]) -> bool:
    from pytensor.tensor.random.type import RandomType

    return any(isinstance(v.type, RandomType) for v in graph_inputs(list(outputs)))


@functools.cache
def _versions() -> str:
    """Python, the libraries whose rewrites and Ops shape the graph, and kohpymc's source."""
    import numba
    import pymc

    source = hashlib.sha256()
    package = Path(__file__).parent
    for path in sorted(package.rglob("*.py")):
        source.update(str(path.relative_to(package)).encode())
        source.update(path.read_bytes())
    return (
        f"format {_FORMAT} python {sys.version} pytensor {pytensor.__version__} "
        f"pymc {pymc.__version__} numba {numba.__version__} numpy {np.__version__} "
        f"kohpymc {source.hexdigest()}"
    )


def _directory() -> Path:
    return Path(pytensor.config.compiledir) / "kohpymc-graphs"


def _store(path: Path, function: Any, n_inputs: int, shared: list[SharedVariable]) -> None:
    """Write ``function``'s rewritten graph, its inputs as placeholders, atomically."""
    fgraph = function.maker.fgraph
    variables = [spec.variable for spec in function.maker.inputs]
    position = {id(v): k for k, v in enumerate(shared)}
    try:
        shared_index = [position[id(v)] for v in variables[n_inputs:]]
        placeholders = [v.type() for v in fgraph.inputs]
        outputs = clone_replace(
            list(fgraph.outputs), dict(zip(fgraph.inputs, placeholders, strict=True))
        )
        payload = pickle.dumps(
            {"placeholders": placeholders, "outputs": outputs, "n_inputs": n_inputs,
             "shared_index": shared_index},
            protocol=pickle.HIGHEST_PROTOCOL,
        )  # fmt: skip
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as file:
            file.write(payload)
        os.replace(file.name, path)
        _prune(path.parent)
    except Exception as err:  # noqa: BLE001 - a graph not cached is compiled next time
        _log.debug("graph not cached: %s", err)


def _prune(directory: Path) -> None:
    """Remove the least recently used files beyond :data:`_KEEP` (each load touches one)."""
    files = sorted(directory.glob("*.pkl"), key=lambda p: p.stat().st_mtime, reverse=True)
    for stale in files[_KEEP:]:
        stale.unlink(missing_ok=True)


def _rewriting(mode: str | Mode) -> Mode:
    """``mode``'s rewrites with Python thunks: the rewritten graph, nothing compiled."""
    from pytensor.compile.mode import get_mode
    from pytensor.link.basic import PerformLinker

    base = get_mode(mode)
    linker = PerformLinker()
    # the rewrites a linker requires or cannot run are chosen by its class attributes
    linker.required_rewrites = base.linker.required_rewrites  # type: ignore[misc]
    linker.incompatible_rewrites = base.linker.incompatible_rewrites  # type: ignore[misc]
    return Mode(linker=linker, optimizer=base.provided_optimizer)


def _linker(mode: str | Mode) -> str:
    """The name of ``mode``'s linker, to link a rewritten graph again without rewrites."""
    if isinstance(mode, str):
        return "numba" if mode == "NUMBA" else "cvm"
    names = {"NumbaLinker": "numba", "PerformLinker": "py", "CVM": "cvm", "VMLinker": "vm"}
    return names.get(type(mode.linker).__name__, "cvm")


def _load(
    path: Path, inputs: Sequence[Variable], outputs: Sequence[Variable], linker: str,
    kwargs: dict[str, Any],
) -> Any:  # fmt: skip
    """The cached graph linked with the caller's inputs and shared variables, or None."""
    if not path.exists():
        return None
    try:
        payload = pickle.loads(path.read_bytes())
        os.utime(path)  # recently used: kept by _prune
        shared = _shared(outputs)
        sources = list(inputs) + [shared[k] for k in payload["shared_index"]]
        replace = dict(zip(payload["placeholders"], sources, strict=True))
        linked = clone_replace(payload["outputs"], replace)
        return pytensor.function(
            list(inputs), linked,
            mode=Mode(linker=linker, optimizer=None),  # type: ignore[arg-type]  # None: no rewrites
            accept_inplace=True, **kwargs,
        )  # fmt: skip
    except Exception as err:  # noqa: BLE001 - compiled again (and rewritten) below
        _log.debug("cached graph %s not used: %s", path.name, err)
        return None
