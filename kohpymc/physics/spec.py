"""The physics model ``y = G(x; θ)``: named inputs, parameters with priors, checks.

:class:`PhysicsModel` validates the specification and turns user inputs and parameter
values into arrays; evaluating, differentiating and building the PyTensor graph are
left to its backend (:mod:`kohpymc.physics.backends`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import numpy as np
import pytensor.tensor as pt

from kohpymc.physics.backends import BACKENDS, Backend, call_function
from kohpymc.physics.errors import NonFiniteOutputError, PhysicsModelError
from kohpymc.physics.finite_differences import default_relative_step, finite_difference_jacobian
from kohpymc.priors import Prior, as_prior

__all__ = ["PhysicsModel", "PhysicsModelError", "singularity_offsets"]


def singularity_offsets(n: int) -> list[np.ndarray]:
    """Relative moves off a removable singularity of ``n`` parameters, smallest first.

    A check point of the library (the prior centre, PyMC's initial point) can fall on a
    removable singularity of a correct model: ``ka / (ka - ke)`` when ``ka`` and ``ke``
    have the same prior.  Each parameter moves by ``step`` (1e-3, 1e-2, 0.1) times a
    weight of its own (``+1/n, -2/n, +3/n, ...``), so parameters at equal values part;
    callers scale the moves to their coordinates.

    Examples
    --------
    >>> [m.tolist() for m in singularity_offsets(2)][0]
    [0.0005, -0.001]
    """
    weights = np.array([(k + 1) / n * (-1) ** k for k in range(n)])
    return [step * weights for step in (1e-3, 1e-2, 1e-1)]


#: points of the prior searched for one where a model undefined at the prior centre is finite
_SEARCH_POINTS = 64


def _prior_quantile_points(p: int) -> np.ndarray:
    """The prior median, then a seeded Sobol design in 5 %–95 % quantile space, nearest first."""
    from scipy.stats import qmc

    design = 0.05 + 0.9 * qmc.Sobol(p, seed=0).random(_SEARCH_POINTS)
    design = design[np.argsort(np.max(np.abs(design - 0.5), axis=1), kind="stable")]
    return np.vstack([np.full(p, 0.5), design])


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
        it the gradient uses finite differences
        (:mod:`kohpymc.physics.finite_differences`).
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
        (its likelihood becomes zero).  The pre-sampling check raises when the model is
        non-finite at the prior centre, unless ``"reject"``: then it looks for a point of
        the priors where the model is finite (:meth:`regular_point`).
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
        if not isinstance(backend, str) or backend not in BACKENDS:
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
        #: the strategy that evaluates, differentiates and builds the tensor
        self.evaluator: Backend = BACKENDS[backend]
        self.fd_scheme = fd_scheme
        if fd_relative_step is None:
            fd_relative_step = default_relative_step(fd_scheme)
        if not fd_relative_step > 0:
            raise ValueError("fd_relative_step must be > 0")
        self.fd_relative_step = float(fd_relative_step)
        self.on_nonfinite = on_nonfinite
        self.name = name or getattr(function, "__name__", "physics")
        self.n_calls = 0

    # ------------------------------------------------------- parameters and inputs
    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of θ in order."""
        return tuple(self.parameters)

    def prior_mean(self) -> dict[str, float]:
        """Prior mean of every parameter (the default expansion/check point)."""
        return {k: p.mean() for k, p in self.parameters.items()}

    def regular_point(
        self, inputs: Mapping[str, Any], point: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        """``point`` (default the prior centre), or a point next to it where the model is finite.

        A check point of the library can fall on a removable singularity of a correct
        model: ``ka / (ka - ke)`` at the prior centre when ``ka`` and ``ke`` have the same
        prior.  Then each parameter is moved by :func:`singularity_offsets` times its prior
        sd, so parameters with the same prior part, and the first such point (inside the
        priors) where the model is finite is returned.  A model that returns NaN/inf
        there with ``on_nonfinite="reject"`` (undefined in part of its prior box) gets the
        first finite point of :func:`_prior_quantile_points` instead.  When there is none,
        the error at ``point`` is raised (for a non-finite model with
        ``on_nonfinite="raise"``, saying how to declare it undefined in part of the box).

        Examples
        --------
        >>> import numpy as np
        >>> from kohpymc import PhysicsModel, LogUniform
        >>> def conc(x, p):
        ...     return p["ka"] / (p["ka"] - p["ke"]) * (np.exp(-p["ke"] * x["t"])
        ...                                            - np.exp(-p["ka"] * x["t"]))
        >>> prior = LogUniform(0.01, 10)
        >>> physics = PhysicsModel(conc, {"ka": prior, "ke": prior}, inputs=["t"])
        >>> point = physics.regular_point({"t": [1.0, 2.0]})
        >>> point["ka"] != point["ke"]
        True
        """
        point = self.prior_mean() if point is None else self._as_params(point)
        try:
            with np.errstate(all="ignore"):  # 0/0 there is reported only if nothing else runs
                self.evaluate(inputs, point)
            return point
        except PhysicsModelError as err:
            first = err
        names = list(self.parameters)
        for offsets in singularity_offsets(len(names)):
            moved = {
                k: point[k] + float(w) * self.parameters[k].sd()
                for k, w in zip(names, offsets, strict=True)
            }
            if not all(self.parameters[k].in_support(v) for k, v in moved.items()):
                continue
            try:
                self.evaluate(inputs, moved)
            except PhysicsModelError:
                continue
            return moved
        if isinstance(first, NonFiniteOutputError):
            return self._finite_prior_point(inputs, point, first)
        raise first

    def _finite_prior_point(
        self, inputs: Mapping[str, Any], point: dict[str, float], error: NonFiniteOutputError
    ) -> dict[str, float]:
        """A point inside the priors where a model non-finite at ``point`` is finite.

        With ``on_nonfinite="raise"`` the error says how to declare a model undefined in
        part of its prior box.  With ``"reject"`` the prior median comes first, then
        the points of a seeded Sobol design in prior-quantile space (5 %–95 %), nearest
        the median first; the first finite one is returned.
        """
        if self.on_nonfinite == "raise":
            raise NonFiniteOutputError(
                f"{error}. If the model is undefined in part of the prior box, pass "
                "on_nonfinite='reject' (in a study file [physics] on_nonfinite = \"reject\"); "
                "otherwise check the priors and units"
            ) from error
        for q in _prior_quantile_points(len(self.parameters)):
            moved = {
                k: prior.quantile(float(u))
                for (k, prior), u in zip(self.parameters.items(), q, strict=True)
            }
            try:
                self.evaluate(inputs, moved)
            except PhysicsModelError:
                continue
            return moved
        raise NonFiniteOutputError(
            f"{error}; the model is non-finite at the prior centre, the prior median and "
            f"{_SEARCH_POINTS} points across the priors' 5 %–95 % quantiles: no point of the "
            "prior box where it is defined was found (check the priors and units)"
        ) from error

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

    # ------------------------------------------------------------ through the backend
    def evaluate(
        self,
        inputs: Mapping[str, Any],
        params: Mapping[str, float] | Sequence[float],
        *,
        check_finite: bool = True,
    ) -> np.ndarray:
        """Run the model with numpy inputs and checks.

        Raises :class:`PhysicsModelError` naming the parameter values when the function
        raises, returns the wrong shape or (with ``check_finite``) NaN/inf.  A pytensor
        model always checks for NaN/inf.

        Examples
        --------
        >>> import numpy as np
        >>> from kohpymc.examples import beam
        >>> beam.physics_model().evaluate({"x": [400.0], "P": [2.5]}, {"E": 200.0})
        array([12.])
        """
        arrays, n = self._as_inputs(inputs)
        p = self._as_params(params)
        return self.evaluator.evaluate(self, arrays, n, p, check_finite=check_finite)

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
        return self.evaluator.jacobian(self, arrays, n, p)

    def finite_difference_jacobian(
        self, inputs: Mapping[str, Any], params: Mapping[str, float]
    ) -> np.ndarray:
        """Finite-difference ``∂G/∂θ`` with the configured scheme and step.

        See :func:`kohpymc.physics.finite_differences.finite_difference_jacobian`.

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
        return finite_difference_jacobian(
            lambda q: call_function(self, arrays, n, q),
            p,
            {k: prior.scale() for k, prior in self.parameters.items()},
            scheme=self.fd_scheme,
            relative_step=self.fd_relative_step,
        )

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
        return self.evaluator.tensor(self, theta, X)

    def variance_tensor(self, theta: pt.TensorVariable, X: pt.TensorVariable) -> Any:
        """Symbolic variance of ``G(X; θ)`` at the rows, or ``None`` (an exact model).

        A surrogate of the physics (an emulator, see :class:`kohpymc.Emulator`) returns
        its predictive variance, one value per row; :func:`kohpymc.model.compose_model`
        adds it to the measurement-noise variance the formulation sees.

        Examples
        --------
        >>> import pytensor.tensor as pt
        >>> from kohpymc.examples import beam
        >>> beam.physics_model().variance_tensor(pt.as_tensor([200.0]), pt.zeros((1, 2))) is None
        True
        """
        return None

    def covariance_tensor(self, theta: pt.TensorVariable, X: pt.TensorVariable) -> Any:
        """Symbolic covariance of ``G(X; θ)`` between the rows, or ``None``.

        A surrogate that knows how its errors correlate across rows (a GP emulator at
        one θ) returns an ``(n, n)`` matrix; formulations that accept it
        (:attr:`kohpymc.discrepancy.Discrepancy.accepts_physics_covariance`) add it to
        the likelihood covariance, the others get :meth:`variance_tensor` added to the
        noise variance.

        Examples
        --------
        >>> import pytensor.tensor as pt
        >>> from kohpymc.examples import beam
        >>> beam.physics_model().covariance_tensor(pt.as_tensor([200.0]), pt.zeros((1, 2)))
        """
        return None

    def posterior_problems(
        self,
        data: Any,
        mean: Mapping[str, float],
        sd: Mapping[str, float],
        *,
        label: str = "the posterior",
        warn: bool = True,
    ) -> list[str]:
        """Why this model may be unfit where a posterior lies (none for an exact model).

        A surrogate of the physics (an emulator) scores itself against the simulator at
        the posterior ``mean`` of θ (``sd`` its posterior sds) on the ``data``'s rows,
        and warns (with ``warn``) when it is unfit there.  :func:`kohpymc.calibrate`
        records the problems in ``idata.attrs["physics_problems"]``, and
        :func:`kohpymc.run_study` reports them in the formulation's status.

        Examples
        --------
        >>> from kohpymc.examples import beam
        >>> beam.physics_model().posterior_problems(None, {"E": 200.0}, {"E": 5.0})
        []
        """
        return []

    def __repr__(self) -> str:
        return (
            f"PhysicsModel({self.name!r}, inputs={list(self.inputs)}, "
            f"parameters={self.parameters}, backend={self.backend!r})"
        )
