"""Fingerprints: hashes of what a result depends on, to reuse it when nothing changed.

A study reuses a finished formulation (and a check a finished replicate) only when the
fingerprint stored with it equals the one computed now.  Each piece is hashed on its own
(:func:`physics_fingerprint`, :func:`data_fingerprint`, :func:`formulation_fingerprint`)
so a caller combines exactly the pieces its result depends on with :func:`digest`: a
changed discrepancy prior then invalidates that formulation only, a changed physics prior
or data file every formulation that uses it.

The physics function is known by its own source *and* the source file it lives in (a
helper it calls may change), falling back to its qualified name when no source exists.
"""

from __future__ import annotations

import hashlib
import inspect
import json
from typing import Any

import numpy as np

from kohpymc.data import CalibrationData

__all__ = [
    "digest",
    "source_fingerprint",
    "physics_fingerprint",
    "data_fingerprint",
    "formulation_fingerprint",
    "kohpymc_version",
]


def digest(content: Any) -> str:
    """SHA-256 of a JSON rendering of ``content`` (keys sorted, others by ``repr``).

    Examples
    --------
    >>> digest({"a": 1, "b": [1.5]}) == digest({"b": [1.5], "a": 1})
    True
    """
    text = json.dumps(content, sort_keys=True, default=repr)
    return hashlib.sha256(text.encode()).hexdigest()


def _array_hash(values: Any) -> str:
    array = np.ascontiguousarray(np.asarray(values, dtype=float))
    return hashlib.sha256(array.tobytes() + str(array.shape).encode()).hexdigest()


def source_fingerprint(function: Any) -> str:
    """A hash of a function's source and of the file that defines it.

    Examples
    --------
    >>> source_fingerprint(digest) == source_fingerprint(digest) != source_fingerprint(repr)
    True
    """
    if function is None:
        return ""
    function = inspect.unwrap(function)  # a wrapper that names what it wraps (__wrapped__)
    # the qualified name and the source, not the module's name: a function loaded from a
    # file gets a module name that differs from process to process
    parts = [str(getattr(function, "__qualname__", ""))]
    try:
        parts.append(inspect.getsource(function))
    except (OSError, TypeError):
        parts.append(str(getattr(function, "__module__", "")))
    try:
        path = inspect.getsourcefile(function)
        if path is not None:
            with open(path, "rb") as handle:
                parts.append(hashlib.sha256(handle.read()).hexdigest())
    except (OSError, TypeError):
        pass
    return digest(parts)


def _prior(prior: Any) -> Any:
    args = getattr(prior, "args", None)
    if isinstance(args, dict):
        return [getattr(prior, "kind", type(prior).__name__), {k: repr(v) for k, v in args.items()}]
    return repr(prior)


def physics_fingerprint(physics: Any) -> str:
    """A hash of a physics model: function and Jacobian sources, inputs, priors, options.

    A model whose results depend on more than its code (an emulator's training runs)
    says so through a ``fingerprint_parts()`` method, whose value is hashed too.

    Examples
    --------
    >>> from kohpymc.examples import beam
    >>> physics_fingerprint(beam.physics_model()) == physics_fingerprint(beam.physics_model())
    True
    """
    extra = getattr(physics, "fingerprint_parts", None)
    return digest(
        {
            "extra": extra() if callable(extra) else None,
            "name": physics.name,
            "backend": physics.backend,
            "function": source_fingerprint(physics.function),
            "jacobian": source_fingerprint(physics.jacobian),
            "inputs": list(physics.inputs),
            "priors": {k: _prior(v) for k, v in physics.parameters.items()},
            "options": [physics.fd_scheme, physics.fd_relative_step, physics.on_nonfinite],
        }
    )


def data_fingerprint(data: CalibrationData) -> str:
    """A hash of a data set: every input column, the output, noise sd and replicates.

    Examples
    --------
    >>> a = CalibrationData({"x": [1.0, 2.0]}, [0.5, 0.7])
    >>> data_fingerprint(a) == data_fingerprint(CalibrationData({"x": [1.0, 2.0]}, [0.5, 0.8]))
    False
    """
    replicates = None if data.replicates is None else [str(v) for v in data.replicates]
    return digest(
        {
            "inputs": {k: _array_hash(v) for k, v in data.inputs.items()},
            "y": _array_hash(data.y),
            "output": data.output_name,
            "noise_sd": None if data.noise_sd is None else repr(float(data.noise_sd)),
            "replicates": replicates,
        }
    )


def formulation_fingerprint(formulation: Any) -> str:
    """A hash of a discrepancy formulation: its plain (TOML) form, else its ``repr``.

    Examples
    --------
    >>> from kohpymc import ConstantBias
    >>> formulation_fingerprint(ConstantBias()) == formulation_fingerprint(ConstantBias())
    True
    """
    if formulation is None:
        return digest(None)
    try:
        described: Any = formulation.to_dict()
    except (TypeError, AttributeError):  # not expressible in TOML, or no to_dict at all
        described = repr(formulation)
    return digest([type(formulation).__qualname__, described])


def kohpymc_version() -> str:
    """The installed kohpymc version (``"0.0.0"`` when running from a source tree).

    Examples
    --------
    >>> isinstance(kohpymc_version(), str)
    True
    """
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("kohpymc")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0.0.0"
