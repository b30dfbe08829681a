"""A physics model with several outputs: ``G_k(x; θ)``, one θ shared by every output.

The user function returns a mapping output name -> array (one value per row); each
output is then an ordinary :class:`~kohpymc.PhysicsModel` (:meth:`MultiOutputPhysics.output`)
with the same parameters and priors, so everything written for one output (the
black-box Op with its gradient, finite differences, autodiff for PyTensor functions,
the identifiability checks) works per output unchanged.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

from kohpymc.physics import PhysicsModel, PhysicsModelError
from kohpymc.priors import Prior

__all__ = ["MultiOutputPhysics"]


class _Select:
    """``function(inputs, params)[output]``, picklable (Dask workers get it by value)."""

    def __init__(self, function: Callable[..., Any], output: str) -> None:
        self.function, self.output = function, output
        self.__wrapped__ = function  # fingerprints hash the wrapped function's source
        self.__name__ = f"{getattr(function, '__name__', 'physics')}[{output}]"

    def __call__(self, inputs: Any, params: Any) -> Any:
        result = self.function(inputs, params)
        if not isinstance(result, Mapping):
            raise PhysicsModelError(
                f"a multi-output physics function must return a mapping output name -> "
                f"array, got {type(result).__name__}"
            )
        if self.output not in result:
            raise PhysicsModelError(
                f"the physics function returned outputs {sorted(result)}, not {self.output!r}"
            )
        return result[self.output]


class _Once:
    """``function(inputs, params)`` called on the first call only; later calls reuse it.

    Every output of one evaluation reads the same result (one simulator run).
    """

    def __init__(self, function: Callable[..., Any]) -> None:
        self.function = function
        self.result: Any = None

    def __call__(self, inputs: Any, params: Any) -> Any:
        if self.result is None:
            self.result = self.function(inputs, params)
        return self.result


def _reading(model: PhysicsModel, once: _Once, output: str) -> PhysicsModel:
    """A copy of an output's model whose function reads ``output`` from ``once``."""
    reader = copy.copy(model)
    reader.function = _Select(once, output)
    return reader


class MultiOutputPhysics:
    """Several outputs ``G_k(x; θ)`` of one physics model with shared parameters θ.

    Parameters
    ----------
    function : callable
        ``function(inputs, params) -> {output: array}``, one array per output with one
        value per row (see :class:`~kohpymc.PhysicsModel` for ``inputs``/``params``).
    parameters : mapping
        Parameter name -> prior, shared by all outputs.
    inputs : sequence of str
        Input names.
    outputs : sequence of str
        Output names (the data's output columns), in stacking order.
    jacobian : callable, optional
        ``jacobian(inputs, params) -> {output: ∂G_k/∂θ}`` (each an ``(n, p)`` array or a
        dict parameter -> array); without it finite differences.
    **options :
        ``backend``, ``fd_scheme``, ``fd_relative_step``, ``on_nonfinite``, ``name`` as
        for :class:`~kohpymc.PhysicsModel`.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import Uniform
    >>> def f(inputs, params):
    ...     return {"a": params["k"] * inputs["x"], "b": params["k"] ** 2 + 0 * inputs["x"]}
    >>> physics = MultiOutputPhysics(f, {"k": Uniform(0, 2)}, inputs=["x"], outputs=["a", "b"])
    >>> physics.evaluate({"x": np.array([1.0, 2.0])}, {"k": 1.5})["b"]
    array([2.25, 2.25])
    """

    def __init__(
        self,
        function: Callable[..., Any],
        parameters: Mapping[str, Prior | dict[str, Any] | Callable[..., Any]],
        inputs: Sequence[str],
        outputs: Sequence[str],
        *,
        jacobian: Callable[..., Any] | None = None,
        backend: Literal["numpy", "pytensor"] = "numpy",
        name: str | None = None,
        **options: Any,
    ) -> None:
        if isinstance(outputs, str):
            outputs = [outputs]
        self.outputs: tuple[str, ...] = tuple(str(o) for o in outputs)
        if not self.outputs:
            raise ValueError("a multi-output physics model needs at least one output name")
        if len(set(self.outputs)) != len(self.outputs):
            raise ValueError(f"output names repeat: {list(self.outputs)}")
        #: the user function (``None`` for a model made of per-output models)
        self.function: Callable[..., Any] | None = function
        self.name = name or getattr(function, "__name__", "physics")
        self.models: dict[str, PhysicsModel] = {}
        for out in self.outputs:
            self.models[out] = PhysicsModel(
                _Select(function, out),
                parameters,
                inputs,
                jacobian=None if jacobian is None else _Select(jacobian, out),
                backend=backend,
                name=f"{self.name}[{out}]",
                **options,
            )
        first = self.models[self.outputs[0]]
        clash = [k for k in self.outputs if k in first.inputs or k in first.parameters]
        if clash:
            raise ValueError(f"output name(s) {clash} are also input or parameter names")
        #: shared parameter priors (the first output's; every output has the same)
        self.parameters = first.parameters
        self.inputs = first.inputs

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of θ in order."""
        return tuple(self.parameters)

    def prior_mean(self) -> dict[str, float]:
        """Prior mean of every parameter."""
        return {k: p.mean() for k, p in self.parameters.items()}

    def output(self, name: str) -> PhysicsModel:
        """The single-output :class:`~kohpymc.PhysicsModel` ``G_name(x; θ)``.

        Examples
        --------
        >>> from kohpymc.examples import beam_multi_output as bm
        >>> bm.physics_model().output("u").name
        'beam_outputs[u]'
        """
        try:
            return self.models[name]
        except KeyError:
            raise KeyError(f"no output {name!r}; outputs are {list(self.outputs)}") from None

    def evaluate(self, inputs: Mapping[str, Any], params: Any) -> dict[str, Any]:
        """Every output at the rows ``inputs``: ``{output: array}`` (checked).

        A numpy function runs once for all outputs (an expensive simulator is not run
        once per output); each output is checked as its own model checks it.

        Examples
        --------
        >>> from kohpymc.examples import beam_multi_output as bm
        >>> out = bm.physics_model().evaluate({"x": [250.0], "P": [6.0]}, {"E": 200.0})
        >>> sorted(out), round(float(out["u"][0]), 6)
        (['strain', 'u'], 600.0)
        """
        if self.function is None or not self._one_function():
            return {k: m.evaluate(inputs, params) for k, m in self.models.items()}
        once = _Once(self.function)
        return {k: _reading(m, once, k).evaluate(inputs, params) for k, m in self.models.items()}

    def _one_function(self) -> bool:
        """Whether every output is read from one numpy function (then it can run once).

        Not for a model made of per-output models (an emulator each), nor for one whose
        outputs were replaced (discovery embeds an output's model with added effects).
        """
        return self.function is not None and all(
            m.backend == "numpy"
            and isinstance(m.function, _Select)
            and m.function.function is self.function
            for m in self.models.values()
        )

    @classmethod
    def from_models(cls, models: Mapping[str, PhysicsModel], *, name: str) -> MultiOutputPhysics:
        """Single-output models sharing θ and inputs as one model (e.g. an emulator each).

        Examples
        --------
        >>> from kohpymc.examples import beam_multi_output as bm
        >>> physics = bm.physics_model()
        >>> same = MultiOutputPhysics.from_models(physics.models, name="copy")
        >>> same.outputs, same.parameter_names
        (('u', 'strain'), ('E',))
        """
        if not models:
            raise ValueError("from_models needs at least one output model")
        first = next(iter(models.values()))
        shape = (tuple(first.parameters), tuple(first.inputs))
        for key, model in models.items():
            if (tuple(model.parameters), tuple(model.inputs)) != shape:
                raise ValueError(
                    f"output {key!r} has parameters {list(model.parameters)} and inputs "
                    f"{list(model.inputs)}; the first output has {list(first.parameters)} "
                    f"and {list(first.inputs)}"
                )
        new = object.__new__(cls)
        new.outputs = tuple(str(k) for k in models)
        new.function = None
        new.name = name
        new.models = dict(models)
        new.parameters = first.parameters
        new.inputs = first.inputs
        return new

    def select(self, outputs: Sequence[str]) -> MultiOutputPhysics:
        """The same model restricted to some outputs (e.g. one output alone)."""
        new = object.__new__(MultiOutputPhysics)
        new.__dict__.update(self.__dict__)
        new.outputs = tuple(outputs)
        new.models = {k: self.output(k) for k in new.outputs}
        return new

    def __repr__(self) -> str:
        return (
            f"MultiOutputPhysics({self.name!r}, inputs={list(self.inputs)}, "
            f"outputs={list(self.outputs)}, parameters={self.parameters})"
        )
