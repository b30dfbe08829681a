r"""A shared-input multi-output GP discrepancy: the intrinsic coregionalisation model.

Instead of one independent discrepancy per output, the outputs' discrepancies are one
Gaussian process over (x, output) with a separable covariance (the intrinsic
coregionalisation model, Álvarez, Rosasco & Lawrence 2012, §4.2):

.. math::

    \mathrm{Cov}[\delta_k(x), \delta_l(x')] = s_k s_l \big(B_{kl}\, k(x, x')
        + 4\,[k = l]\big), \qquad B = W W^\top + \mathrm{diag}(\kappa),

with ``k`` a stationary kernel over the chosen inputs (squared exponential by default, or a
Matérn 5/2, Matérn 3/2 or exponential one: ``kernel=``; ARD length scales
``delta_ls``, prior ``InverseGamma(4, 2 · range)`` as for M4), ``W`` a ``K × rank``
matrix (``delta_W``, standard normal entries) and ``κ ≥ 0`` (``delta_kappa``,
``HalfNormal(1)``).  ``s_k`` is the sd of output ``k``'s data, so ``B`` is unit-free and
outputs in different units share it; the ``4 [k = l]`` term is a constant mean per
output with prior ``N(0, (2 s_k)²)``, integrated out.  With ``rank = 0`` (``W`` absent)
the outputs' discrepancies are independent GPs sharing length scales; ``W`` lets the
discrepancy of one output inform another's.

Likelihood (one joint Gaussian over the stacked rows of all outputs):

.. math::

    y \sim N\big(G(X; \theta),\ S (B[o, o'] \odot K(X, X') + 4\,[o = o']) S
        + \mathrm{diag}(\sigma_{obs, o_i}^2)\big).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import pymc as pm
import pytensor.tensor as pt

from kohpymc.gaussian import GaussianLikelihood
from kohpymc.model import PRED_DIM, _check_physics, _scales, new_input_matrix

__all__ = ["Coregionalized", "JointRecord"]

#: the observed variable's dimension (rows of all outputs, stacked)
JOINT_DIM = "obs"
#: prior variance (in units of s_k²) of each output's constant discrepancy mean
MEAN_VARIANCE = 4.0
_JITTER = 1e-6
#: ``kernel=`` names and the stationary PyMC covariances they select
KERNELS = {
    "ExpQuad": pm.gp.cov.ExpQuad,
    "Matern52": pm.gp.cov.Matern52,
    "Matern32": pm.gp.cov.Matern32,
    "Exponential": pm.gp.cov.Exponential,
}


@dataclass(frozen=True)
class JointRecord:
    """What :class:`Coregionalized` built.

    Attributes
    ----------
    mean : TensorVariable
        ``G`` at the stacked rows.
    covariance : TensorVariable
        The joint covariance.
    noise_scale : numpy.ndarray
        Per stacked row: the output's known σ_obs, else the sd of its data.
    output_index : numpy.ndarray
        Output number of each stacked row.
    """

    mean: Any
    covariance: Any
    noise_scale: np.ndarray
    output_index: np.ndarray


class Coregionalized:
    """Shared-input multi-output GP discrepancy (intrinsic coregionalisation).

    Parameters
    ----------
    inputs : sequence of str
        Inputs of the shared kernel.
    rank : int
        Columns of ``W`` (0: independent GPs with shared length scales).
    kernel : {"ExpQuad", "Matern52", "Matern32", "Exponential"}
        The stationary kernel ``k`` (PyMC's covariance of that name); a rougher kernel
        for a discrepancy that is not smooth in the inputs.

    Examples
    --------
    >>> from kohpymc.examples import beam_multi_output as bm
    >>> from kohpymc.multi_output import compose_multi_output_model
    >>> built = compose_multi_output_model(bm.physics_model(), bm.generate_data(),
    ...                                    Coregionalized(["x"]))
    >>> sorted(v.name for v in built.model.free_RVs)
    ['E', 'delta_W', 'delta_kappa', 'delta_ls']
    >>> built.model.named_vars_to_dims["y"]
    ('obs',)
    """

    label = "ICM"
    description = "coregionalised multi-output GP"
    default_target_accept = 0.95

    def __init__(self, inputs: Sequence[str], rank: int = 1, kernel: str = "ExpQuad") -> None:
        if kernel not in KERNELS:
            raise ValueError(
                f"Coregionalized: kernel must be one of {sorted(KERNELS)}, got {kernel!r}"
            )
        self.kernel = kernel
        if isinstance(inputs, str):
            inputs = [inputs]
        self.inputs = tuple(inputs)
        if not self.inputs:
            raise ValueError("Coregionalized: give at least one input for the kernel")
        if int(rank) != rank or rank < 0:
            raise ValueError(f"Coregionalized: rank must be a non-negative integer, got {rank}")
        self.rank = int(rank)

    def noise_partner(self) -> None:
        """No single discrepancy variance adds to σ_obs²."""
        return None

    # ---------------------------------------------------------------- the math
    @staticmethod
    def coregionalization(W: Any, kappa: Any) -> Any:
        """``B = W Wᵀ + diag(κ)`` (``W`` may have zero columns).

        Examples
        --------
        >>> import numpy as np
        >>> Coregionalized.coregionalization(np.ones((2, 1)), np.array([1.0, 2.0])).eval()
        array([[2., 1.],
               [1., 3.]])
        """
        W = pt.as_tensor_variable(W)
        return pt.dot(W, W.T) + pt.diag(pt.as_tensor_variable(kappa))

    def _cross(self, kernel, B, scale, Xa, oa, Xb, ob):
        """``s_a s_b (B[o_a, o_b] k(Xa, Xb) + 4 [o_a = o_b])``."""
        same = pt.eq(oa[:, None], ob[None, :]).astype("float64")
        core = B[oa][:, ob] * kernel(Xa, Xb) + MEAN_VARIANCE * same
        return scale[oa][:, None] * core * scale[ob][None, :]

    # ------------------------------------------------------------------- build
    def build_joint(
        self,
        model: pm.Model,
        physics: Any,
        data: Any,
        theta: Any,
        priors: Mapping[str, Any],
        new_inputs: Mapping[str, Any] | None,
    ) -> Any:
        """Add the joint likelihood (and predictions) to ``model``; return the built model."""
        from kohpymc.multi_output.model import MultiOutputModel

        names = self._input_names(physics, data)
        rows = _stack_outputs(physics, data, theta, priors, names)
        model.add_coord(JOINT_DIM, np.arange(rows.y.size))
        kernel, B = self._kernel_priors(model, rows)
        scale_t = pt.as_tensor_variable(np.asarray(rows.scales))
        sigma_t = pt.stack([pt.as_tensor_variable(s, dtype="float64") for s in rows.sigmas])
        o_t = pt.as_tensor_variable(rows.output.astype("int64"))
        X_t = pt.as_tensor_variable(rows.X)
        K = self._cross(kernel, B, scale_t, X_t, o_t, X_t, o_t)
        cov = K + pt.diag(sigma_t[o_t] ** 2 + _JITTER * scale_t[o_t] ** 2)
        mu = pt.concatenate(rows.physics)
        GaussianLikelihood("y", mu=mu, cov=cov, observed=rows.y, dims=JOINT_DIM)
        record = JointRecord(mu, cov, np.concatenate(rows.noise_scale), rows.output)
        parts = _output_parts(rows, mu)
        if new_inputs:
            gp = _JointGP(partial(self._cross, kernel, B, scale_t), X_t, o_t, mu, cov)
            _add_predictions(model, physics, theta, rows, gp, new_inputs)
        return MultiOutputModel(model, parts, joint=record)

    def _input_names(self, physics: Any, data: Any) -> tuple[str, ...]:
        """The physics inputs, then the kernel's other inputs (all must be in the data)."""
        names = tuple(dict.fromkeys(physics.inputs + self.inputs))
        missing = [k for k in names if k not in data.input_names]
        if missing:
            raise KeyError(f"Coregionalized: input(s) {missing} are not in the data")
        return names

    def _kernel_priors(self, model: pm.Model, rows: _Stacked) -> tuple[Any, Any]:
        """Add the length scales, ``κ`` and ``W`` to ``model``; return the kernel and ``B``."""
        outputs, names = rows.outputs, rows.names
        _, _, span = _scales(rows.X, names)
        active = [names.index(k) for k in self.inputs]
        model.add_coord("gp_input", list(self.inputs))
        model.add_coord("output", list(outputs))
        spans = np.array([span[k] for k in self.inputs])
        ls = pm.InverseGamma("delta_ls", alpha=4.0, beta=2.0 * spans, dims="gp_input")
        kappa = pm.HalfNormal("delta_kappa", 1.0, dims="output")
        if self.rank:
            model.add_coord("coregionalization_rank", np.arange(self.rank))
            W = pm.Normal("delta_W", 0.0, 1.0, dims=("output", "coregionalization_rank"))
        else:
            W = pt.zeros((len(outputs), 0))
        B = self.coregionalization(W, kappa)
        kernel = KERNELS[self.kernel](len(names), ls=ls, active_dims=active)
        return kernel, B

    def __repr__(self) -> str:
        kernel = "" if self.kernel == "ExpQuad" else f", kernel={self.kernel!r}"
        return f"Coregionalized(inputs={list(self.inputs)}, rank={self.rank}{kernel})"


@dataclass(frozen=True)
class _Stacked:
    """The outputs' data rows stacked, with each output's physics, σ_obs and data sd."""

    outputs: tuple[str, ...]
    names: tuple[str, ...]  # columns of X: the physics inputs, then the kernel's others
    X: np.ndarray  # (n, len(names))
    output: np.ndarray  # (n,) output number of each row
    y: np.ndarray  # (n,)
    physics: list[Any]  # per output: G at its rows (tensor)
    sigmas: list[Any]  # per output: σ_obs (known number or random variable)
    scales: list[float]  # per output: sd of its data
    noise_scale: list[np.ndarray]  # per output, per row: known σ_obs, else the data sd


@dataclass(frozen=True)
class _JointGP:
    """The joint GP's tensors that predictions condition on."""

    cross: Callable[..., Any]  # (Xa, oa, Xb, ob) -> covariance block
    X: Any
    output: Any
    mean: Any
    covariance: Any


def _stack_outputs(
    physics: Any, data: Any, theta: Any, priors: Mapping[str, Any], names: tuple[str, ...]
) -> _Stacked:
    """Stack every output's rows; add each output's σ_obs prior (model ``<k>``)."""
    from kohpymc.multi_output.model import _sigma_obs, _y_scale

    Xs, idx, ys, G, sigmas, scales, noise_scale = [], [], [], [], [], [], []
    n_phys = len(physics.inputs)
    for j, k in enumerate(data.outputs):
        part = data[k]
        _check_physics(physics.output(k), part)
        X = part.matrix(names)
        Xs.append(X)
        idx.append(np.full(part.n, j))
        ys.append(part.y)
        G.append(physics.output(k).tensor(theta, pt.as_tensor_variable(X[:, :n_phys])))
        scale = _y_scale(part.y)
        with pm.Model(name=k):
            sigmas.append(_sigma_obs(k, part.noise_sd, priors[k], scale))
        scales.append(scale)
        noise_scale.append(np.full(part.n, part.noise_sd or scale))
    return _Stacked(
        tuple(data.outputs),
        names,
        np.vstack(Xs),
        np.concatenate(idx),
        np.concatenate(ys),
        G,
        sigmas,
        scales,
        noise_scale,
    )


def _output_parts(rows: _Stacked, mu: Any) -> dict[str, Any]:
    """One :class:`~kohpymc.multi_output.model.OutputPart` per output: its rows of ``mu``."""
    from kohpymc.multi_output.model import OutputPart

    parts = {}
    for j, k in enumerate(rows.outputs):
        sel = rows.output == j
        parts[k] = OutputPart(
            k,
            None,
            None,
            rows.names,
            rows.sigmas[j],
            float(rows.noise_scale[j][0]),
            mu[np.flatnonzero(sel)],
        )
    return parts


def _add_predictions(
    model: pm.Model,
    physics: Any,
    theta: Any,
    rows: _Stacked,
    gp: _JointGP,
    new_inputs: Mapping[str, Any],
) -> None:
    """Add ``<k>::physics``, ``y_model``, ``discrepancy``, ``y_pred`` at one output's inputs."""
    ((k, inputs),) = new_inputs.items()
    j = rows.outputs.index(k)
    Xn = new_input_matrix(inputs, rows.names)
    model.add_coord(PRED_DIM, np.arange(Xn.shape[0]))
    Xn_t = pt.as_tensor_variable(Xn)
    on = pt.as_tensor_variable(np.full(Xn.shape[0], j, dtype="int64"))
    Ks = gp.cross(gp.X, gp.output, Xn_t, on)
    Kss = gp.cross(Xn_t, on, Xn_t, on)
    chol = pt.linalg.cholesky(gp.covariance)
    alpha = pt.linalg.cho_solve((chol, True), rows.y - gp.mean)
    v = pt.linalg.solve_triangular(chol, Ks, lower=True)
    cond_cov = Kss - pt.dot(v.T, v) + _JITTER * rows.scales[j] ** 2 * pt.eye(Xn.shape[0])
    G_new = physics.output(k).tensor(theta, Xn_t[:, : len(physics.inputs)])
    with pm.Model(name=k):
        G_det = pm.Deterministic("physics", G_new, dims=PRED_DIM)
        delta = pm.MvNormal("gp_conditional", mu=pt.dot(Ks.T, alpha), cov=cond_cov, dims=PRED_DIM)
        y_model = pm.Deterministic("y_model", G_det + delta, dims=PRED_DIM)
        pm.Deterministic("discrepancy", delta, dims=PRED_DIM)
        pm.Normal("y_pred", mu=y_model, sigma=rows.sigmas[j], dims=PRED_DIM)
