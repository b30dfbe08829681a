r"""A Gaussian-process emulator of a simulator, usable as a physics model.

:class:`Emulator` fits a GP to simulator runs over (inputs x, parameters θ):

* columns scaled to the unit box of the design (:func:`~kohpymc.emulator.design.design_box`),
  outputs standardised to mean 0, sd 1;
* an ARD kernel, squared exponential ``s² exp(-r²/2)`` or Matérn 5/2
  ``s² (1 + √5 r + 5r²/3) exp(-√5 r)``, ``r² = Σ_k (Δu_k / ℓ_k)²``, plus a nugget ``g``;
* hyperparameters ``(ℓ, s², g)`` by MAP: multi-start L-BFGS-B on the log marginal
  likelihood (analytic gradient) plus weak priors, ``ln ℓ_k ~ N(ln 0.5, 1.5²)``,
  ``ln s² ~ N(0, 2²)``, ``ln ρ ~ N(ln 1e-6, 4²)`` for the nugget ``g = ρ s²``, within
  bounds (``ρ ≥ 1e-8`` keeps the kernel matrix well conditioned).

The predictive mean ``η̂(x, θ)`` and variance ``v(x, θ)`` (the latent variance plus the
nugget, in output units) are also written as PyTensor expressions of θ from the stored
training matrices, so gradients with respect to θ are exact autodiff.
:meth:`Emulator.physics_model` returns an :class:`EmulatedPhysics`: a
:class:`~kohpymc.PhysicsModel` (backend ``"pytensor"``) whose mean is ``η̂`` and whose
:meth:`~EmulatedPhysics.variance_tensor` is ``v``.  :func:`kohpymc.model.compose_model`
adds that variance to the measurement-noise variance every formulation sees, so the
likelihood is ``y ~ N(η̂(X, θ) + δ, diag v(X, θ) + Σ_δ + σ² I)``: a poor emulator widens
the posterior instead of biasing it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytensor
import pytensor.tensor as pt
from scipy import linalg, optimize

from kohpymc.emulator.design import log_scaled
from kohpymc.emulator.runs import SimulatorRuns
from kohpymc.physics import PhysicsModel
from kohpymc.warning_filters import warn_user

__all__ = ["EmulatedPhysics", "Emulator", "EmulatorWarning", "GPHyperparameters", "KERNELS"]


class EmulatorWarning(UserWarning):
    """An emulator that is not fit for calibration (bands miss, large errors, failed runs)."""


#: kernels :class:`Emulator` knows
KERNELS = ("se", "matern52")

_SQRT5 = np.sqrt(5.0)
#: prior of ln ℓ_k (unit-box length scales): mean, sd
_LS_PRIOR = (np.log(0.5), 1.5)
_AMP_PRIOR = (0.0, 2.0)
_NUGGET_PRIOR = (np.log(1e-6), 4.0)  # of ln ρ, the nugget relative to s²
_BOUNDS_LS = (np.log(1e-3), np.log(1e3))
_BOUNDS_AMP = (np.log(1e-3), np.log(1e6))
_BOUNDS_NUGGET = (np.log(1e-8), np.log(0.5))


@dataclass(frozen=True)
class GPHyperparameters:
    """The fitted kernel settings (standardised output, unit-box inputs).

    Attributes
    ----------
    lengthscales : numpy.ndarray
        One per column (inputs, then parameters), in unit-box units.
    amplitude : float
        ``s²``, the kernel variance.
    nugget : float
        ``g``, the white-noise variance.
    log_posterior : float
        Log marginal likelihood plus log prior at the optimum.
    """

    lengthscales: np.ndarray
    amplitude: float
    nugget: float
    log_posterior: float


def _kernel_numpy(kind: str, U: np.ndarray, V: np.ndarray, ls: np.ndarray, amp: float):
    """``K(U, V)`` and the scaled squared differences ``D_k / ℓ_k²`` (n, m, q)."""
    D = ((U[:, None, :] - V[None, :, :]) / ls) ** 2
    return _kernel_of_r2(kind, np.sum(D, axis=-1), amp), D


def _kernel_of_r2(kind: str, r2: np.ndarray, amp: float) -> np.ndarray:
    """The kernel as a function of the scaled squared distance ``r²``."""
    if kind == "se":
        return amp * np.exp(-0.5 * r2)
    r = np.sqrt(r2)
    return amp * (1.0 + _SQRT5 * r + 5.0 * r2 / 3.0) * np.exp(-_SQRT5 * r)


def _pairwise_squares(U: np.ndarray) -> np.ndarray:
    """``(q, n, n)`` squared differences of the rows of ``U``, one matrix per column.

    They do not depend on the hyperparameters: computed once per fit, every evaluation
    of :func:`_neg_log_posterior` then forms ``r²`` by one matrix-vector product.
    """
    return (U.T[:, :, None] - U.T[:, None, :]) ** 2


def _neg_log_posterior(
    params: np.ndarray, kind: str, U: np.ndarray, y: np.ndarray, pairs: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """Negative (log marginal likelihood + log prior) and its gradient in log space.

    ``pairs``: :func:`_pairwise_squares` of ``U`` (computed here when not given).
    """
    q, n = U.shape[1], len(y)
    pairs = _pairwise_squares(U) if pairs is None else pairs
    log_ls, log_amp, log_g = params[:q], params[q], params[q + 1]
    # the nugget is relative to the amplitude, g = s² ρ, which bounds the condition number
    ls, amp = np.exp(log_ls), float(np.exp(log_amp))
    g = amp * float(np.exp(log_g))
    inv_ls2 = 1.0 / ls**2
    flat = pairs.reshape(q, n * n)
    r2 = (inv_ls2 @ flat).reshape(n, n)
    R = _kernel_of_r2(kind, r2, 1.0)
    K = amp * R + (g + 1e-10) * np.eye(n)
    try:
        chol = linalg.cholesky(K, lower=True)
    except linalg.LinAlgError:
        return 1e25, np.zeros_like(params)
    alpha = linalg.cho_solve((chol, True), y)
    Kinv = _inverse_from_cholesky(chol)
    nll = 0.5 * y @ alpha + np.sum(np.log(np.diag(chol))) + 0.5 * n * np.log(2 * np.pi)
    W = np.outer(alpha, alpha) - Kinv  # d nll / dθ = -½ tr(W dK/dθ)
    grad = np.empty_like(params)
    if kind == "se":
        base = amp * R
    else:
        r = np.sqrt(r2)
        base = amp * (5.0 / 3.0) * (1.0 + _SQRT5 * r) * np.exp(-_SQRT5 * r)
    # dK/d ln ℓ_k = base ∘ (pairs_k / ℓ_k²)
    grad[:q] = -0.5 * (flat @ (W * base).ravel()) * inv_ls2
    trace_w = float(np.trace(W))
    grad[q] = -0.5 * (float(np.sum(W * R)) * amp + trace_w * g)
    grad[q + 1] = -0.5 * trace_w * g
    # weak priors (negative log densities and their gradients)
    m, s = _LS_PRIOR
    nll += np.sum((log_ls - m) ** 2) / (2 * s**2)
    grad[:q] += (log_ls - m) / s**2
    m, s = _AMP_PRIOR
    nll += (log_amp - m) ** 2 / (2 * s**2)
    grad[q] += (log_amp - m) / s**2
    m, s = _NUGGET_PRIOR
    nll += (log_g - m) ** 2 / (2 * s**2)
    grad[q + 1] += (log_g - m) / s**2
    return float(nll), grad


def _inverse_from_cholesky(chol: np.ndarray) -> np.ndarray:
    """``K⁻¹`` from the lower Cholesky factor of ``K`` (LAPACK ``potri``, symmetrized)."""
    lower, info = linalg.lapack.dpotri(chol, lower=1)
    if info != 0:
        return linalg.cho_solve((chol, True), np.eye(len(chol)))
    lower = np.tril(lower)
    return lower + np.tril(lower, -1).T


def _fit_hyperparameters(
    kind: str, U: np.ndarray, y: np.ndarray, restarts: int, seed: int
) -> GPHyperparameters:
    q = U.shape[1]
    rng = np.random.default_rng(seed)
    bounds = [_BOUNDS_LS] * q + [_BOUNDS_AMP, _BOUNDS_NUGGET]
    starts = [np.r_[np.full(q, np.log(0.5)), 0.0, np.log(1e-4)]]
    for _ in range(max(0, restarts - 1)):
        starts.append(
            np.r_[rng.uniform(np.log(0.05), np.log(3.0), q), rng.normal(0, 0.5), np.log(1e-4)]
        )
    pairs = _pairwise_squares(U)
    best = None
    for x0 in starts:
        res = optimize.minimize(
            _neg_log_posterior,
            x0,
            args=(kind, U, y, pairs),
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
        )
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    p = best.x
    return GPHyperparameters(
        lengthscales=np.exp(p[:q]),
        amplitude=float(np.exp(p[q])),
        nugget=float(np.exp(p[q]) * np.exp(p[q + 1])),
        log_posterior=float(-best.fun),
    )


class SharedTrainingData:
    """An emulator's training data as shared variables, made once and never pickled.

    Run-time inputs of a compiled graph, not constants: numba would inline the
    ``N × N`` matrices into its code (a minute of compiling the dielectric emulator,
    again for every emulator, never cached), and its disk cache can serve the next run.
    A subclass names the arrays in :meth:`_training_values`.

    Examples
    --------
    >>> class Data(SharedTrainingData):
    ...     def _training_values(self):
    ...         return {"U": np.eye(2)}
    >>> Data()._training_tensors()["U"].name
    'emulator_U'
    """

    def _training_values(self) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def _training_tensors(self) -> dict[str, Any]:
        """:meth:`_training_values` as shared variables ``emulator_<name>``, made once."""
        tensors = self.__dict__.get("_tensors")
        if tensors is None:
            values = self._training_values()
            tensors = {k: shared_array(v, f"emulator_{k}") for k, v in values.items()}
            self.__dict__["_tensors"] = tensors
        return tensors

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_tensors", None)  # shared variables: made again on demand
        return state


class Emulator(SharedTrainingData):
    r"""A GP emulator ``η̂(x, θ)`` of a simulator, fitted to its runs.

    Parameters
    ----------
    runs : SimulatorRuns
        Successful simulator runs (:func:`~kohpymc.emulator.runs.run_design`).
    physics : PhysicsModel
        The simulator's physics model: its priors become those of
        :meth:`physics_model`; its inputs and parameters name the columns.
    box : mapping, optional
        Column -> ``(lower, upper)`` defining the unit box (default: the runs' range).
        A positive column spanning two decades or more is scaled by its logarithm
        (:func:`~kohpymc.emulator.design.log_scaled`), as the designs spread it.
    kernel : {"matern52", "se"}
        ARD Matérn 5/2 (default) or squared exponential.  On smooth test functions the
        squared exponential was more accurate but its 90 % bands covered only 0.6–0.9
        of held-out runs (overconfident), Matérn 5/2 covered 0.88–0.96.
    restarts : int
        Starts of the L-BFGS-B search for the hyperparameters (the first at
        ``ℓ = 0.5``, ``s² = 1``, the others random).
    seed : int
        Seed of the random starts.
    hyperparameters : GPHyperparameters, optional
        Use these instead of fitting.
    log_output : bool
        Fit the GP to ln y (every run's output must be positive): for outputs spanning
        decades over the design (rates, currents).  Predictions are the log-normal mean,
        variance and covariance in output units.  :func:`~kohpymc.emulator.emulate`
        chooses it by default (``"auto"``).

    Attributes
    ----------
    hyper : GPHyperparameters
    n_runs : int

    Examples
    --------
    >>> from kohpymc.emulator import design_box, run_design, space_filling_design
    >>> from kohpymc.examples import beam
    >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
    >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 30))
    >>> em = Emulator(runs, physics)
    >>> mean, var = em.predict({"x": [400.0], "P": [2.5]}, {"E": 200.0})
    >>> bool(abs(mean[0] - 12.0) < 0.1), bool(var[0] < 0.1)
    (True, True)
    """

    def __init__(
        self,
        runs: SimulatorRuns,
        physics: PhysicsModel,
        *,
        box: Mapping[str, tuple[float, float]] | None = None,
        kernel: Literal["se", "matern52"] = "matern52",
        restarts: int = 5,
        seed: int = 0,
        hyperparameters: GPHyperparameters | None = None,
        log_output: bool = False,
    ) -> None:
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {list(KERNELS)}, got {kernel!r}")
        if tuple(runs.inputs) != tuple(physics.inputs) or tuple(runs.parameters) != tuple(
            physics.parameters
        ):
            raise ValueError(
                f"Emulator: the runs have inputs {list(runs.inputs)} and parameters "
                f"{list(runs.parameters)}, the physics model {physics.name!r} has "
                f"{list(physics.inputs)} and {list(physics.parameters)}"
            )
        X, y = runs.X, runs.y
        if len(y) < 2:
            raise ValueError(
                f"Emulator of {physics.name!r} needs at least 2 successful runs, got {len(y)}"
                + (f": {runs.failure_summary()}" if len(runs.failed) else "")
            )
        if len(runs.failed):
            warn_user(
                f"emulator of {physics.name!r}: {runs.failure_summary()}; it is fitted to the "
                f"{len(y)} others and knows nothing of where these failed (a posterior there "
                "rests on no run; see runs.failed)",
                EmulatorWarning,
            )
        self.physics = physics
        self.runs = runs
        self.kernel = kernel
        self.columns: tuple[str, ...] = tuple(runs.inputs + runs.parameters)
        self.n_inputs = len(runs.inputs)
        box = dict(box or {})
        lo = np.array(
            [box[k][0] if k in box else X[:, j].min() for j, k in enumerate(self.columns)]
        )
        hi = np.array(
            [box[k][1] if k in box else X[:, j].max() for j, k in enumerate(self.columns)]
        )
        self.log_columns = log_scaled(lo, hi)
        lo, hi = self._transform(lo), self._transform(hi)
        self.lower = lo.astype(float)
        self.width = np.where(hi > lo, hi - lo, 1.0).astype(float)
        self.log_output = bool(log_output)
        if self.log_output and not np.all(y > 0):
            raise ValueError(
                f"Emulator(log_output=True): {int(np.sum(y <= 0))} run(s) of "
                f"{physics.name!r} have outputs <= 0"
            )
        g = np.log(y) if self.log_output else y
        self.y_mean = float(np.mean(g))
        sd = float(np.std(g))
        self.y_sd = sd if sd > 0 else 1.0
        self.U = (self._transform(X) - self.lower) / self.width
        self.z = (g - self.y_mean) / self.y_sd
        self.hyper = hyperparameters or _fit_hyperparameters(kernel, self.U, self.z, restarts, seed)
        self._factorize()

    @property
    def n_runs(self) -> int:
        """Number of runs the GP is fitted to."""
        return len(self.z)

    def _factorize(self) -> None:
        h = self.hyper
        R, _ = _kernel_numpy(self.kernel, self.U, self.U, h.lengthscales, h.amplitude)
        K = R + (h.nugget + 1e-10) * np.eye(self.n_runs)
        self._chol = linalg.cholesky(K, lower=True)
        self._alpha = linalg.cho_solve((self._chol, True), self.z)
        self._chol_inv = linalg.solve_triangular(self._chol, np.eye(self.n_runs), lower=True)

    def _training_values(self) -> dict[str, np.ndarray]:
        """The runs' coordinates, ``α = K⁻¹z`` and ``L⁻¹``."""
        return {"U": self.U, "alpha": self._alpha, "chol_inv": self._chol_inv}

    # ------------------------------------------------------------------- numpy
    def _transform(self, values: np.ndarray) -> np.ndarray:
        """Columns in the scale of the unit box: ln for :attr:`log_columns`."""
        values = np.asarray(values, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.log_columns, np.log(np.abs(values)), values)

    def parameters_to_unit(self, values: np.ndarray) -> np.ndarray:
        """θ rows (columns in ``runs.parameters`` order) in the unit box of the fit.

        Examples
        --------
        >>> from kohpymc.emulator import emulate
        >>> from kohpymc.examples import beam
        >>> em = emulate(beam.physics_model(), beam.generate_data(seed=1), runs=10)
        >>> u = em.parameters_to_unit(np.array([[150.0]]))
        >>> bool(np.allclose(em.parameters_from_unit(u), 150.0))
        True
        """
        cols = self._parameter_columns()
        values = np.asarray(values, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            scaled = np.where(self.log_columns[cols], np.log(np.abs(values)), values)
        return (scaled - self.lower[cols]) / self.width[cols]

    def parameters_from_unit(self, unit: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`parameters_to_unit` (exp only of the log-scaled columns)."""
        cols = self._parameter_columns()
        scaled = self.lower[cols] + np.asarray(unit, dtype=float) * self.width[cols]
        logs = self.log_columns[cols]
        return np.where(logs, np.exp(np.where(logs, scaled, 0.0)), scaled)

    def _parameter_columns(self) -> list[int]:
        return [self.columns.index(k) for k in self.runs.parameters]

    def _output_moments(self, mean: Any, var: Any, lib: Any = np) -> tuple[Any, Any]:
        """Latent mean/variance (standardised) as output-unit mean and variance."""
        m, v = self.y_mean + self.y_sd * mean, self.y_sd**2 * var
        if not self.log_output:
            return m, v
        return lib.exp(m + v / 2.0), lib.expm1(v) * lib.exp(2.0 * m + v)

    def _matrix(self, inputs: Mapping[str, Any], params: Any) -> np.ndarray:
        arrays, n = self.physics._as_inputs(inputs)
        theta = self.physics._as_params(params)
        cols = [arrays[k] for k in self.physics.inputs]
        cols += [np.full(n, theta[k]) for k in self.physics.parameters]
        return np.column_stack(cols)

    def predict_matrix(
        self, Z: np.ndarray, without: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean and variance at rows ``Z`` (columns: inputs, then parameters).

        The variance is that of a new simulator output (latent variance plus nugget),
        in output units squared.  ``without`` (a boolean mask over the runs) conditions
        on the other runs only, with the same hyperparameters and scaling: what the
        emulator would predict had those runs not been made.

        Examples
        --------
        >>> from kohpymc.emulator import design_box, run_design, space_filling_design
        >>> from kohpymc.examples import beam
        >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
        >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 20))
        >>> mean, var = Emulator(runs, physics).predict_matrix(runs.X[:2])
        >>> bool(np.allclose(mean, runs.y[:2], atol=1e-2))
        True
        """
        Z = np.atleast_2d(np.asarray(Z, dtype=float))
        if Z.shape[1] != len(self.columns):
            raise ValueError(f"predict_matrix: rows need columns {list(self.columns)}")
        h = self.hyper
        U, alpha, chol_inv = self.U, self._alpha, self._chol_inv
        if without is not None and np.any(without):
            U, alpha, chol_inv = self._conditioned_on(~np.asarray(without, dtype=bool))
        Us = (self._transform(Z) - self.lower) / self.width
        Ks, _ = _kernel_numpy(self.kernel, Us, U, h.lengthscales, h.amplitude)
        mean = Ks @ alpha
        V = chol_inv @ Ks.T
        var = h.amplitude + h.nugget - np.sum(V**2, axis=0)
        var = np.maximum(var, h.nugget)
        return self._output_moments(mean, var)

    def _conditioned_on(self, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``U``, ``K⁻¹z`` and ``L⁻¹`` of the runs in ``keep`` (hyperparameters kept)."""
        h = self.hyper
        U = self.U[keep]
        R, _ = _kernel_numpy(self.kernel, U, U, h.lengthscales, h.amplitude)
        chol = linalg.cholesky(R + (h.nugget + 1e-10) * np.eye(len(U)), lower=True)
        alpha = linalg.cho_solve((chol, True), self.z[keep])
        return U, alpha, linalg.solve_triangular(chol, np.eye(len(U)), lower=True)

    def predict(
        self, inputs: Mapping[str, Any], params: Mapping[str, float] | Sequence[float] | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean and variance at input rows ``inputs`` and one θ ``params``.

        Examples
        --------
        See :class:`Emulator`.
        """
        return self.predict_matrix(self._matrix(inputs, params))

    def leave_one_out(self) -> tuple[np.ndarray, np.ndarray]:
        """Closed-form leave-one-out mean and variance of every run (fixed hyperparameters).

        ``μ_{-i} = y_i - [K⁻¹z]_i / [K⁻¹]_ii``, ``v_{-i} = 1 / [K⁻¹]_ii`` (Rasmussen &
        Williams 2006, §5.4.2), in output units.

        Examples
        --------
        >>> from kohpymc.emulator import design_box, run_design, space_filling_design
        >>> from kohpymc.examples import beam
        >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
        >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 20))
        >>> mean, var = Emulator(runs, physics).leave_one_out()
        >>> mean.shape == var.shape == (20,)
        True
        """
        diag = np.sum(self._chol_inv**2, axis=0)  # diag of K⁻¹ = L⁻ᵀ L⁻¹
        mean_z = self.z - self._alpha / diag
        return self._output_moments(mean_z, 1.0 / diag)

    def loo_log_density(self) -> float:
        """Mean leave-one-out log predictive density of the runs, in output units.

        A proper score of the leave-one-out means and variances together (Gneiting &
        Raftery 2007): with ``log_output`` the density of ln y less ln y (the log-normal
        density of y), so emulators on either scale compare.

        Examples
        --------
        >>> from kohpymc.emulator import design_box, run_design, space_filling_design
        >>> from kohpymc.examples import beam
        >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
        >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 20))
        >>> bool(np.isfinite(Emulator(runs, physics).loo_log_density()))
        True
        """
        diag = np.sum(self._chol_inv**2, axis=0)
        error = self._alpha / diag  # latent z_i - μ_-i, standardised units
        var = self.y_sd**2 / diag
        latent = -0.5 * (np.log(2.0 * np.pi * var) + (self.y_sd * error) ** 2 / var)
        if self.log_output:
            latent = latent - np.log(self.runs.y)
        return float(np.mean(latent))

    # ----------------------------------------------------------------- pytensor
    def _scaled_rows(self, theta: Any, X: Any) -> list[Any]:
        """Unit-box columns of the rows ``(X, θ)`` as tensors (θ broadcast over rows)."""
        theta = pt.as_tensor_variable(theta)
        X = pt.as_tensor_variable(X)

        def scaled(values: Any, j: int) -> Any:
            values = pt.log(values) if self.log_columns[j] else values
            return (values - self.lower[j]) / self.width[j]

        cols = [scaled(X[:, j], j) for j in range(self.n_inputs)]
        ones = pt.ones_like(X[:, 0])
        for i in range(len(self.columns) - self.n_inputs):
            cols.append(ones * scaled(theta[i], self.n_inputs + i))
        return cols

    def _cross_kernel(self, theta: Any, X: Any) -> Any:
        """``K(rows, runs)`` as a tensor, shape ``(n, N)``."""
        h = self.hyper
        U = self._training_tensors()["U"]
        r2 = 0.0
        for j, col in enumerate(self._scaled_rows(theta, X)):
            r2 = r2 + ((col[:, None] - U[None, :, j]) / h.lengthscales[j]) ** 2
        if self.kernel == "se":
            return h.amplitude * pt.exp(-0.5 * r2)
        r = pt.sqrt(r2 + 1e-12)
        return h.amplitude * (1.0 + _SQRT5 * r + 5.0 * r2 / 3.0) * pt.exp(-_SQRT5 * r)

    def mean_tensor(self, theta: Any, X: Any) -> Any:
        """Symbolic predictive mean ``η̂(X, θ)``, ``X`` ``(n, d)`` in input order.

        Examples
        --------
        See :meth:`variance_tensor`.
        """
        mean = self._latent_mean(theta, X)
        if not self.log_output:
            return self.y_mean + self.y_sd * mean
        return self._output_moments(mean, self._latent_variance(theta, X), pt)[0]

    def _latent_mean(self, theta: Any, X: Any) -> Any:
        """Standardised predictive mean ``k α`` as a tensor."""
        return pt.dot(self._cross_kernel(theta, X), self._training_tensors()["alpha"])

    def _latent_variance(self, theta: Any, X: Any) -> Any:
        """Standardised predictive variance (latent plus nugget) as a tensor."""
        h = self.hyper
        V = pt.dot(self._training_tensors()["chol_inv"], self._cross_kernel(theta, X).T)
        return pt.maximum(h.amplitude + h.nugget - pt.sum(V**2, axis=0), h.nugget)

    def variance_tensor(self, theta: Any, X: Any) -> Any:
        """Symbolic predictive variance ``v(X, θ)`` (latent plus nugget), output units².

        Examples
        --------
        >>> from kohpymc.emulator import design_box, run_design, space_filling_design
        >>> from kohpymc.examples import beam
        >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
        >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 20))
        >>> em = Emulator(runs, physics)
        >>> X = np.array([[400.0, 2.5]])
        >>> v = em.variance_tensor(pt.as_tensor([200.0]), X).eval()
        >>> bool(np.allclose(v, em.predict({"x": [400.0], "P": [2.5]}, [200.0])[1]))
        True
        """
        var = self._latent_variance(theta, X)
        if not self.log_output:
            return self.y_sd**2 * var
        mean = self._latent_mean(theta, X)
        return self._output_moments(mean, var, pt)[1]

    def covariance_tensor(self, theta: Any, X: Any) -> Any:
        """Symbolic predictive covariance ``Σ_η(X, θ)`` between the rows (output units²).

        Its diagonal is :meth:`variance_tensor` (up to the clipping there).

        Examples
        --------
        >>> from kohpymc.emulator import design_box, run_design, space_filling_design
        >>> from kohpymc.examples import beam
        >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
        >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 20))
        >>> em = Emulator(runs, physics)
        >>> X = np.array([[300.0, 2.5], [400.0, 2.5]])
        >>> C = em.covariance_tensor(pt.as_tensor([200.0]), X).eval()
        >>> v = em.variance_tensor(pt.as_tensor([200.0]), X).eval()
        >>> bool(np.allclose(np.diag(C), v))
        True
        """
        h = self.hyper
        cols = self._scaled_rows(theta, X)
        r2 = 0.0
        for j in range(self.n_inputs):  # θ is shared by all rows: only inputs differ
            r2 = r2 + ((cols[j][:, None] - cols[j][None, :]) / h.lengthscales[j]) ** 2
        if self.kernel == "se":
            prior = h.amplitude * pt.exp(-0.5 * r2)
        else:
            r = pt.sqrt(r2 + 1e-12)
            prior = h.amplitude * (1.0 + _SQRT5 * r + 5.0 * r2 / 3.0) * pt.exp(-_SQRT5 * r)
        V = pt.dot(self._training_tensors()["chol_inv"], self._cross_kernel(theta, X).T)
        n = pt.as_tensor_variable(X).shape[0]
        cov = prior - pt.dot(V.T, V) + h.nugget * pt.eye(n)
        if not self.log_output:
            return self.y_sd**2 * cov
        # log-normal: Cov(e^a, e^b) = e^{μa + μb + (σa² + σb²)/2} (e^{σab} − 1)
        latent = self.y_sd**2 * cov
        m = self.y_mean + self.y_sd * self._latent_mean(theta, X)
        half = m + pt.diagonal(latent) / 2.0
        return pt.exp(half[:, None] + half[None, :]) * pt.expm1(latent)

    def physics_model(
        self,
        *,
        covariance: Literal["full", "diagonal"] = "full",
        name: str | None = None,
    ) -> EmulatedPhysics:
        """The emulator as a physics model (priors of the simulator's parameters).

        Parameters
        ----------
        covariance : {"full", "diagonal"}
            ``"full"``: the emulator's predictive covariance between the calibration
            rows, ``Σ_η(θ)``, enters the likelihood covariance (formulations M0–M6);
            ``"diagonal"``: only its variances, added to the noise variance.  The
            diagonal form treats the emulator errors of the rows as independent, which
            overstates the information of a poor emulator: the likelihood then favours
            θ near design points (measured: biased posteriors with 8–15 runs), so
            ``"full"`` is the default.
        name : str, optional
            Label of the physics model (default: the simulator's name + "(emulated)").

        Examples
        --------
        >>> from kohpymc.emulator import design_box, run_design, space_filling_design
        >>> from kohpymc.examples import beam
        >>> physics, data = beam.physics_model(), beam.generate_data(seed=1)
        >>> runs = run_design(physics, space_filling_design(design_box(physics, data), 20))
        >>> Emulator(runs, physics).physics_model().name
        'euler_bernoulli (emulated)'
        """
        if covariance not in ("full", "diagonal"):
            raise ValueError(f"covariance must be 'full' or 'diagonal', got {covariance!r}")
        return EmulatedPhysics(self, covariance=covariance, name=name)

    def __repr__(self) -> str:
        h = self.hyper
        ls = ", ".join(f"{k}={v:.3g}" for k, v in zip(self.columns, h.lengthscales, strict=True))
        return (
            f"Emulator({self.physics.name!r}, runs={self.n_runs}, kernel={self.kernel!r}, "
            f"lengthscales=({ls}), amplitude={h.amplitude:.3g}, nugget={h.nugget:.3g}"
            + (", log_output=True)" if self.log_output else ")")
        )


def shared_array(value: Any, name: str) -> Any:
    """``value`` as a float64 shared variable (a run-time input of compiled graphs).

    Examples
    --------
    >>> shared_array([1, 2], "x").get_value()
    array([1., 2.])
    """
    return pytensor.shared(np.array(value, dtype=float), name=name)


def _is_numeric(value: Any) -> bool:
    return isinstance(value, int | float | np.floating | np.integer | np.ndarray)


class EmulatedPhysics(PhysicsModel):
    """A physics model whose ``G`` is an emulator's mean, with its predictive variance.

    Evaluating it with numpy values uses the emulator directly (no compilation); in a
    PyMC model it is a PyTensor expression of θ (exact gradients), and
    :meth:`variance_tensor` gives the emulator variance that
    :func:`kohpymc.model.compose_model` adds to the noise variance.

    Examples
    --------
    See :meth:`Emulator.physics_model`.
    """

    def __init__(
        self,
        emulator: Emulator,
        *,
        covariance: Literal["full", "diagonal"] = "full",
        name: str | None = None,
    ) -> None:
        self.emulator = emulator
        self.covariance = covariance
        #: folder of cached simulator runs for :meth:`posterior_problems` (None: no cache)
        self.runs_cache: Path | None = None
        source = emulator.physics
        super().__init__(
            self._emulated,
            dict(source.parameters),
            source.inputs,
            backend="pytensor",
            name=name or f"{source.name} (emulated)",
        )

    def fingerprint_parts(self) -> dict[str, Any]:
        """What this model's results depend on beyond its source code: the emulator.

        Its training runs, scaling, kernel and hyperparameters and the covariance mode
        (read by :func:`kohpymc.fingerprint.physics_fingerprint`, so a study rerun with a
        refitted emulator does not reuse results of the old one).
        """
        from kohpymc.fingerprint import physics_fingerprint

        em = self.emulator
        return {
            "simulator": physics_fingerprint(em.physics),
            "kernel": em.kernel,
            "covariance": self.covariance,
            "U": np.asarray(em.U, dtype=float).round(12).tolist(),
            "z": np.asarray(em.z, dtype=float).round(12).tolist(),
            "scaling": [em.lower.tolist(), em.width.tolist(), em.y_mean, em.y_sd],
            "hyper": repr(em.hyper),
            "log_output": em.log_output,
            "log_columns": np.asarray(em.log_columns).tolist(),
        }

    def _emulated(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> Any:
        if all(_is_numeric(v) for v in params.values()):
            mean, _ = self.emulator.predict(inputs, params)
            return mean
        theta = pt.stack([pt.as_tensor_variable(params[k]) for k in self.parameters])
        X = pt.stack([pt.as_tensor_variable(inputs[k]) for k in self.inputs], axis=1)
        return self.emulator.mean_tensor(theta, X)

    def evaluate(
        self,
        inputs: Mapping[str, Any],
        params: Mapping[str, float] | Sequence[float],
        *,
        check_finite: bool = True,
    ) -> np.ndarray:
        """The emulator mean at the rows (numpy, no compilation)."""
        return self.emulator.predict(inputs, params)[0]

    def jacobian_matrix(
        self, inputs: Mapping[str, Any], params: Mapping[str, float] | Sequence[float]
    ) -> np.ndarray:
        """Finite-difference ``∂η̂/∂θ`` of the emulator mean (numpy, no compilation)."""
        return self.finite_difference_jacobian(inputs, self._as_params(params))

    def variance_tensor(self, theta: Any, X: Any) -> Any:
        """Symbolic emulator variance ``v(X, θ)`` at the rows."""
        return self.emulator.variance_tensor(theta, X)

    def covariance_tensor(self, theta: Any, X: Any) -> Any:
        """Symbolic emulator covariance ``Σ_η(X, θ)`` (``None`` in diagonal mode)."""
        if self.covariance == "diagonal":
            return None
        return self.emulator.covariance_tensor(theta, X)

    def posterior_problems(
        self,
        data: Any,
        mean: Mapping[str, float],
        sd: Mapping[str, float],
        *,
        label: str = "the posterior",
        warn: bool = True,
    ) -> list[str]:
        """The emulator scored against one simulator run at a posterior mean.

        :func:`~kohpymc.emulator.posterior_check.check_at_posterior` (the run cached in
        :attr:`runs_cache` when set, as a study sets it); an :class:`EmulatorWarning`
        with ``warn`` when it finds problems.
        """
        from kohpymc.emulator.posterior_check import check_at_posterior

        check = check_at_posterior(
            self.emulator, data, mean, sd, label=label, cache=self.runs_cache
        )
        if check.problems and warn:
            warn_user(
                f"emulator of {self.emulator.physics.name!r} ({self.emulator.n_runs} "
                f"{getattr(self.emulator, 'runs_noun', 'runs')}) is "
                f"not fit where {label} lies: {'; '.join(check.problems)}; add runs there "
                "(refine_at_posteriors; in a study, [emulator] refine_at_posterior rounds)",
                EmulatorWarning,
            )
        return list(check.problems)
