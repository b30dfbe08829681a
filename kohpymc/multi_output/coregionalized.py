r"""A shared-input multi-output GP discrepancy: the intrinsic coregionalisation model.

Instead of one independent discrepancy per output, the outputs' discrepancies are one
Gaussian process over (x, output) with a separable covariance (the intrinsic
coregionalisation model, Álvarez, Rosasco & Lawrence 2012, §4.2):

.. math::

    \mathrm{Cov}[\delta_k(x), \delta_l(x')] = s_k s_l \big(B_{kl}\, k(x, x')
        + 4\,[k = l]\big), \qquad B = W W^\top + \mathrm{diag}(\kappa),

with ``k`` a squared-exponential kernel over the chosen inputs (ARD length scales
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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
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

    def __init__(self, inputs: Sequence[str], rank: int = 1) -> None:
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
        from kohpymc.multi_output.model import MultiOutputModel, OutputPart, _sigma_obs, _y_scale

        outputs = data.outputs
        phys_inputs = physics.inputs
        names = tuple(dict.fromkeys(phys_inputs + self.inputs))
        missing = [k for k in names if k not in data.input_names]
        if missing:
            raise KeyError(f"Coregionalized: input(s) {missing} are not in the data")
        Xs, idx, ys, G, sigmas, scales, noise_scale = [], [], [], [], [], [], []
        n_phys = len(phys_inputs)
        for j, k in enumerate(outputs):
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
        X_all, o_all, y_all = np.vstack(Xs), np.concatenate(idx), np.concatenate(ys)
        center, sd, span = _scales(X_all, names)
        active = [names.index(k) for k in self.inputs]
        model.add_coord(JOINT_DIM, np.arange(y_all.size))
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
        kernel = pm.gp.cov.ExpQuad(len(names), ls=ls, active_dims=active)
        scale_t = pt.as_tensor_variable(np.asarray(scales))
        sigma_t = pt.stack([pt.as_tensor_variable(s, dtype="float64") for s in sigmas])
        o_t = pt.as_tensor_variable(o_all.astype("int64"))
        X_t = pt.as_tensor_variable(X_all)
        K = self._cross(kernel, B, scale_t, X_t, o_t, X_t, o_t)
        cov = K + pt.diag(sigma_t[o_t] ** 2 + _JITTER * scale_t[o_t] ** 2)
        mu = pt.concatenate(G)
        GaussianLikelihood("y", mu=mu, cov=cov, observed=y_all, dims=JOINT_DIM)
        record = JointRecord(mu, cov, np.concatenate(noise_scale), o_all)
        parts = {}
        for j, k in enumerate(outputs):
            rows = o_all == j
            parts[k] = OutputPart(
                k, None, None, names, sigmas[j], float(noise_scale[j][0]), mu[np.flatnonzero(rows)]
            )
        if new_inputs:
            ((k, inputs),) = new_inputs.items()
            j = outputs.index(k)
            Xn = new_input_matrix(inputs, names)
            model.add_coord(PRED_DIM, np.arange(Xn.shape[0]))
            Xn_t = pt.as_tensor_variable(Xn)
            on = pt.as_tensor_variable(np.full(Xn.shape[0], j, dtype="int64"))
            Ks = self._cross(kernel, B, scale_t, X_t, o_t, Xn_t, on)
            Kss = self._cross(kernel, B, scale_t, Xn_t, on, Xn_t, on)
            chol = pt.linalg.cholesky(cov)
            alpha = pt.linalg.cho_solve((chol, True), y_all - mu)
            v = pt.linalg.solve_triangular(chol, Ks, lower=True)
            cond_cov = Kss - pt.dot(v.T, v) + _JITTER * scales[j] ** 2 * pt.eye(Xn.shape[0])
            G_new = physics.output(k).tensor(theta, Xn_t[:, :n_phys])
            with pm.Model(name=k):
                G_det = pm.Deterministic("physics", G_new, dims=PRED_DIM)
                delta = pm.MvNormal(
                    "gp_conditional", mu=pt.dot(Ks.T, alpha), cov=cond_cov, dims=PRED_DIM
                )
                y_model = pm.Deterministic("y_model", G_det + delta, dims=PRED_DIM)
                pm.Deterministic("discrepancy", delta, dims=PRED_DIM)
                pm.Normal("y_pred", mu=y_model, sigma=sigmas[j], dims=PRED_DIM)
        return MultiOutputModel(model, parts, joint=record)

    def __repr__(self) -> str:
        return f"Coregionalized(inputs={list(self.inputs)}, rank={self.rank})"
