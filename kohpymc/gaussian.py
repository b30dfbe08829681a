r"""A multivariate normal likelihood whose log density and gradient are one LAPACK pass.

Every formulation but M0 ends in ``y ~ N(μ, C)`` with a dense ``n × n`` covariance (the
GP kernel, or a diagonal plus the low-rank term of integrated-out mean coefficients).
PyMC's :class:`pymc.MvNormal` differentiates through ``cholesky`` and
``solve_triangular``; without a system BLAS those run as several Python-level ops per
gradient (about 0.5–0.8 ms for ``n = 20`` on the development machine, most of it call
overhead).  Here one op returns

.. math::

    \log p = -\tfrac12 r^\top C^{-1} r - \tfrac12 \log|C| - \tfrac n2 \log 2\pi,
    \qquad \alpha = C^{-1} r, \qquad C^{-1},

with ``r = y - μ``, from one Cholesky factorization (``dpotrf``/``dpotrs``/``dpotri``),
and its gradient is written with the two extra outputs (no second factorization):

.. math::

    \partial \log p / \partial r = -\alpha, \qquad
    \partial \log p / \partial C = \tfrac12 (\alpha \alpha^\top - C^{-1}).

:class:`GaussianLikelihood` is :class:`pymc.MvNormal` with this log density (its random
variable is an ``MvNormalRV``, so draws, ``pm.compute_log_likelihood`` and code that
looks for an ``MvNormalRV`` work unchanged).  A covariance that is not positive definite
gives ``-inf``.
"""

from __future__ import annotations

import numpy as np
import pymc as pm
import pytensor.tensor as pt
from pytensor.gradient import DisconnectedType
from pytensor.graph.basic import Apply, Constant
from pytensor.graph.op import Op
from pytensor.tensor.random.basic import MvNormalRV
from scipy.linalg import lapack

__all__ = ["GaussianLogDensity", "gaussian_log_density", "GaussianLikelihood"]

_LOG_2PI = float(np.log(2.0 * np.pi))


class GaussianLogDensity(Op):
    """``(log N(r; 0, C), C⁻¹ r, C⁻¹)`` for a vector ``r`` and an SPD matrix ``C``.

    The gradient is defined for the first output only (the other two exist so that the
    gradient graph reuses the factorization).

    Examples
    --------
    >>> import numpy as np, pytensor.tensor as pt
    >>> C = np.array([[2.0, 0.5], [0.5, 1.0]]); r = np.array([0.3, -0.2])
    >>> logp = GaussianLogDensity()(pt.as_tensor(r), pt.as_tensor(C))[0].eval()
    >>> from scipy.stats import multivariate_normal
    >>> bool(np.isclose(logp, multivariate_normal(np.zeros(2), C).logpdf(r)))
    True
    """

    __props__ = ()

    def make_node(self, r, C):  # noqa: D102
        r = pt.as_tensor_variable(r).astype("float64")
        C = pt.as_tensor_variable(C).astype("float64")
        if r.ndim != 1 or C.ndim != 2:
            raise ValueError("GaussianLogDensity needs a vector r and a matrix C")
        return Apply(self, [r, C], [pt.dscalar(), pt.dvector(), pt.dmatrix()])

    def perform(self, node, inputs, outputs):  # noqa: D102
        r, C = inputs
        n = r.shape[0]
        factor = self._factor(node, C)
        if factor is None:
            outputs[0][0] = np.array(-np.inf)
            outputs[1][0] = np.zeros(n)
            outputs[2][0] = np.zeros((n, n))
            return
        chol, inverse, log_det = factor
        alpha, _ = lapack.dpotrs(chol, r, lower=1)
        outputs[0][0] = np.array(-0.5 * (r @ alpha + log_det + n * _LOG_2PI))
        outputs[1][0] = alpha
        outputs[2][0] = inverse.copy()

    @staticmethod
    def _factor(node, C) -> tuple[np.ndarray, np.ndarray, float] | None:
        """Cholesky factor, inverse and log-determinant of ``C`` (``None``: not SPD).

        A constant covariance (known noise, integrated-out mean coefficients: M1) is
        factorized once per compiled node, not at every evaluation.
        """
        constant = isinstance(node.inputs[1], Constant)
        if constant and hasattr(node.tag, "kohpymc_factor"):
            return node.tag.kohpymc_factor
        chol, info = lapack.dpotrf(np.asarray(C, order="F"), lower=1, clean=1)
        factor = None
        if info == 0 and np.all(np.isfinite(chol)):
            inverse, _ = lapack.dpotri(chol, lower=1)
            inverse = np.tril(inverse) + np.tril(inverse, -1).T
            factor = (chol, inverse, 2.0 * float(np.sum(np.log(np.diagonal(chol)))))
        if constant:
            node.tag.kohpymc_factor = factor
        return factor

    def grad(self, inputs, output_grads):  # noqa: D102
        g_logp, g_alpha, g_inverse = output_grads
        for g in (g_alpha, g_inverse):
            if not isinstance(g.type, DisconnectedType):
                raise NotImplementedError("GaussianLogDensity: gradient of outputs 1, 2")
        _, alpha, inverse = self(*inputs)
        return [-g_logp * alpha, 0.5 * g_logp * (pt.outer(alpha, alpha) - inverse)]

    def connection_pattern(self, node):  # noqa: D102
        return [[True, True, True], [True, True, True]]

    def infer_shape(self, fgraph, node, shapes):  # noqa: D102
        n = shapes[0][0]
        return [(), (n,), (n, n)]


_gaussian_log_density = GaussianLogDensity()


def _register_numba() -> None:
    """Compile :class:`GaussianLogDensity` natively in PyTensor's NUMBA mode (and nutpie)."""
    try:
        from pytensor.link.numba.dispatch import basic as numba_basic
        from pytensor.link.numba.dispatch.basic import register_funcify_default_op_cache_key
        from pytensor.link.numba.dispatch.linalg.decomposition.cholesky import _cholesky
    except ImportError:  # pragma: no cover - numba is a PyTensor dependency here
        return

    @register_funcify_default_op_cache_key(GaussianLogDensity)
    def _numba_gaussian_log_density(op, node, **kwargs):
        @numba_basic.numba_njit
        def gaussian_log_density(r, C):
            n = r.shape[0]
            chol = _cholesky(np.ascontiguousarray(C), True, False)
            diag = np.diag(chol)
            if not np.all(np.isfinite(diag)) or not np.all(diag > 0):
                return np.array(-np.inf), np.zeros(n), np.zeros((n, n))
            inverse = np.linalg.inv(C)
            alpha = inverse @ r
            log_det = 2.0 * np.sum(np.log(diag))
            return np.array(-0.5 * (r @ alpha + log_det + n * _LOG_2PI)), alpha, inverse

        return gaussian_log_density, 1


_register_numba()


def gaussian_log_density(value, mu, cov) -> pt.TensorVariable:
    """Symbolic ``log N(value; mu, cov)`` through :class:`GaussianLogDensity`.

    Examples
    --------
    >>> import numpy as np
    >>> float(gaussian_log_density(np.zeros(1), np.zeros(1), np.eye(1)).eval())  # -log √(2π)
    -0.9189385332046727
    """
    value = pt.as_tensor_variable(value)
    mu = pt.as_tensor_variable(mu)
    return _gaussian_log_density(value - mu, cov)[0]


class _GaussianLikelihoodRV(MvNormalRV):
    """``MvNormalRV`` whose log density is :func:`gaussian_log_density`."""


class GaussianLikelihood(pm.MvNormal):
    """:class:`pymc.MvNormal` (``mu``, ``cov``) with the one-pass log density above.

    Use for observed vectors; draws are those of ``MvNormal``.

    Examples
    --------
    >>> import numpy as np, pymc as pm
    >>> with pm.Model() as model:
    ...     s = pm.HalfNormal("s")
    ...     y = GaussianLikelihood("y", mu=np.zeros(3), cov=s**2 * np.eye(3) + 0.5,
    ...                            observed=np.array([0.1, -0.4, 0.2]))
    >>> with pm.Model() as reference:
    ...     s = pm.HalfNormal("s")
    ...     y = pm.MvNormal("y", mu=np.zeros(3), cov=s**2 * np.eye(3) + 0.5,
    ...                     observed=np.array([0.1, -0.4, 0.2]))
    >>> point = {"s_log__": np.array(0.3)}
    >>> bool(np.isclose(model.compile_logp()(point), reference.compile_logp()(point)))
    True
    """

    rv_type = _GaussianLikelihoodRV
    rv_op = _GaussianLikelihoodRV(method="cholesky")

    @staticmethod
    def logp(value, mu, cov):  # noqa: D102
        if value.ndim != 1:
            raise NotImplementedError("GaussianLikelihood supports one observed vector")
        return gaussian_log_density(value, mu, cov)
