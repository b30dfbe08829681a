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

A covariance that is a diagonal plus a low-rank term, ``C = diag(d) + F Fᵀ`` with ``F``
``n × k`` and ``k < n`` (a principal-component emulator's ``Σ_η`` plus noise, a
marginalized mean's ``B S0 Bᵀ``), is built with :func:`low_rank_covariance`; the matrix
is the same, but it carries its parts, and :class:`GaussianLikelihood` then evaluates
:func:`woodbury_log_density` (Woodbury identity and matrix determinant lemma,
``O(n k²)``) instead of factorizing the ``n × n`` matrix (``O(n³)``).
:func:`add_to_covariance` and :func:`covariance_solve` keep and use the structure.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import pymc as pm
import pytensor.tensor as pt
from pytensor.gradient import DisconnectedType
from pytensor.graph.basic import Apply, Constant
from pytensor.graph.op import Op
from pytensor.tensor.random.basic import MvNormalRV
from scipy.linalg import lapack

__all__ = [
    "GaussianLogDensity",
    "gaussian_log_density",
    "GaussianLikelihood",
    "LowRankCovariance",
    "WoodburyLogDensity",
    "add_to_covariance",
    "covariance_solve",
    "low_rank_covariance",
    "low_rank_parts",
    "woodbury_log_density",
]

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


def _numba_dispatch():
    """PyTensor's numba dispatch module, its Op registration decorator and its Cholesky.

    None without numba; the ``_register_*`` functions below then leave their Op to the
    other backends.
    """
    try:
        from pytensor.link.numba.dispatch import basic as numba_basic
        from pytensor.link.numba.dispatch.basic import register_funcify_default_op_cache_key
        from pytensor.link.numba.dispatch.linalg.decomposition.cholesky import _cholesky
    except ImportError:  # pragma: no cover - numba is a PyTensor dependency here
        return None
    return numba_basic, register_funcify_default_op_cache_key, _cholesky


def _numba_inverse_from_cholesky(numba_basic: Any) -> Any:
    """A numba function ``C⁻¹`` from the lower Cholesky factor of ``C`` (LAPACK ``dpotri``).

    ``dpotri`` reuses the factor the log density needs anyway: at ``n = 240`` (a GP over
    the dielectric example's rows) the factor and inverse took 2.8–3.7 ms, a second
    factorization by ``np.linalg.inv`` 5.5–5.9 ms (one thread, same process).  The
    LAPACK address is looked up once per process and kept out of numba's on-disk cache
    (PyTensor's ``_call_cached_ptr``, as its own LAPACK bindings do).
    """
    import numba
    from numba.core import types
    from numba.core.extending import get_cython_function_address
    from pytensor.link.numba.cache import _call_cached_ptr
    from pytensor.link.numba.dispatch.linalg._LAPACK import nb_f64p, nb_i32p, val_to_int_ptr

    @numba_basic.numba_njit
    def potri_address():
        with numba.objmode(address=types.intp):
            address = get_cython_function_address("scipy.linalg.cython_lapack", "dpotri")
        return address

    potri_type = types.FunctionType(types.void(nb_i32p, nb_i32p, nb_f64p, nb_i32p, nb_i32p))

    @numba_basic.numba_njit
    def inverse_from_cholesky(chol):
        potri = _call_cached_ptr(
            get_ptr_func=potri_address,
            func_type_ref=potri_type,
            unique_func_name_lit="kohpymc.gaussian.dpotri",
        )
        n = chol.shape[0]
        work = np.empty((n, n)).T  # column-major, as LAPACK reads it
        for j in range(n):
            for i in range(j, n):
                work[i, j] = chol[i, j]
        size = np.int32(n)
        uplo, order = val_to_int_ptr(ord("L")), val_to_int_ptr(size)
        lda, info = val_to_int_ptr(size), val_to_int_ptr(0)
        potri(uplo, order, work.ctypes, lda, info)
        for j in range(n):  # dpotri fills the lower triangle only
            for i in range(j):
                work[i, j] = work[j, i]
        return work.T  # symmetric: the same matrix, row-major

    return inverse_from_cholesky


def _register_numba() -> None:
    """Compile :class:`GaussianLogDensity` natively in PyTensor's NUMBA mode (and nutpie)."""
    parts = _numba_dispatch()
    if parts is None:  # pragma: no cover - numba is a PyTensor dependency here
        return
    numba_basic, register_funcify_default_op_cache_key, _cholesky = parts

    inverse_from_cholesky = _numba_inverse_from_cholesky(numba_basic)

    @register_funcify_default_op_cache_key(GaussianLogDensity)
    def _numba_gaussian_log_density(op, node, **kwargs):
        @numba_basic.numba_njit
        def gaussian_log_density(r, C):
            n = r.shape[0]
            r = np.ascontiguousarray(r)  # a strided r: numba's '@' would warn (and be slower)
            chol = _cholesky(np.ascontiguousarray(C), True, False)
            diag = np.diag(chol)
            if not np.all(np.isfinite(diag)) or not np.all(diag > 0):
                return np.array(-np.inf), np.zeros(n), np.zeros((n, n))
            inverse = inverse_from_cholesky(chol)
            alpha = inverse @ r
            log_det = 2.0 * np.sum(np.log(diag))
            return np.array(-0.5 * (r @ alpha + log_det + n * _LOG_2PI)), alpha, inverse

        return gaussian_log_density, 3  # the cache key salt: 3 since r is made contiguous


_register_numba()


class LowRankCovariance(Op):
    """``diag(d) + F Fᵀ`` as a dense matrix whose graph keeps ``d`` and ``F``.

    Code that needs the matrix (draws, leave-one-out, a GP's training covariance) uses
    it as any covariance; :class:`GaussianLikelihood` and :func:`covariance_solve` read
    the parts (:func:`low_rank_parts`) and never form it.

    Examples
    --------
    >>> import numpy as np
    >>> C = LowRankCovariance()(np.array([1.0, 2.0]), np.array([[1.0], [3.0]])).eval()
    >>> C.tolist()
    [[2.0, 3.0], [3.0, 11.0]]
    """

    __props__ = ()

    def make_node(self, d, F):  # noqa: D102
        d = pt.as_tensor_variable(d).astype("float64")
        F = pt.as_tensor_variable(F).astype("float64")
        if d.ndim != 1 or F.ndim != 2:
            raise ValueError("LowRankCovariance needs a vector d and a matrix F")
        return Apply(self, [d, F], [pt.dmatrix()])

    def perform(self, node, inputs, outputs):  # noqa: D102
        d, F = inputs
        C = F @ F.T
        C[np.diag_indices_from(C)] += d
        outputs[0][0] = C

    def grad(self, inputs, output_grads):  # noqa: D102
        _, F = inputs
        (g,) = output_grads
        return [pt.diagonal(g), pt.dot(g + g.T, F)]

    def infer_shape(self, fgraph, node, shapes):  # noqa: D102
        n = shapes[0][0]
        return [(n, n)]


_low_rank_covariance = LowRankCovariance()


def _register_low_rank_numba() -> None:
    """Compile :class:`LowRankCovariance` natively in PyTensor's NUMBA mode (and nutpie)."""
    parts = _numba_dispatch()
    if parts is None:  # pragma: no cover - numba is a PyTensor dependency here
        return
    numba_basic, register_funcify_default_op_cache_key, _ = parts

    @register_funcify_default_op_cache_key(LowRankCovariance)
    def _numba_low_rank_covariance(op, node, **kwargs):
        @numba_basic.numba_njit
        def low_rank_covariance(d, F):
            C = F @ F.T
            for i in range(d.shape[0]):
                C[i, i] += d[i]
            return C

        return low_rank_covariance, 1


_register_low_rank_numba()


def low_rank_covariance(diagonal: Any, factor: Any) -> pt.TensorVariable:
    """The covariance ``diag(diagonal) + factor factorᵀ``, keeping its parts in the graph.

    Parameters
    ----------
    diagonal : tensor-like, ``(n,)``
        Positive variances.
    factor : tensor-like, ``(n, k)``
        The low-rank factor (``k < n`` for the structure to pay).

    Returns
    -------
    TensorVariable
        ``(n, n)``; :func:`low_rank_parts` recovers ``(diagonal, factor)`` from it.

    Examples
    --------
    >>> import numpy as np
    >>> C = low_rank_covariance(np.ones(3), np.ones((3, 1)))
    >>> C.eval()[0].tolist(), len(low_rank_parts(C))
    ([2.0, 1.0, 1.0], 2)
    """
    return cast(pt.TensorVariable, _low_rank_covariance(diagonal, factor))


def low_rank_parts(cov: Any) -> tuple[pt.TensorVariable, pt.TensorVariable] | None:
    """``(diagonal, factor)`` of a :func:`low_rank_covariance`, else ``None``.

    Examples
    --------
    >>> import numpy as np
    >>> low_rank_parts(pt.as_tensor(np.eye(2))) is None
    True
    """
    owner = getattr(cov, "owner", None)
    if owner is not None and isinstance(owner.op, LowRankCovariance):
        d, F = owner.inputs
        return d, F
    return None


def add_to_covariance(cov: Any, diagonal: Any = None, factor: Any = None) -> pt.TensorVariable:
    """``cov + diag(diagonal) + factor factorᵀ``, low-rank when ``cov`` is.

    Parameters
    ----------
    cov : tensor-like, ``(n, n)``
        A covariance, possibly a :func:`low_rank_covariance`.
    diagonal : tensor-like, optional
        ``(n,)`` (or a scalar) added to the diagonal.
    factor : tensor-like, optional
        ``(n, j)`` whose outer product is added (appended to the low-rank factor).

    Examples
    --------
    >>> import numpy as np
    >>> C = add_to_covariance(low_rank_covariance(np.ones(2), np.ones((2, 1))), 1.0,
    ...                       np.array([[1.0], [0.0]]))
    >>> C.eval().tolist(), low_rank_parts(C)[1].eval().shape
    ([[4.0, 1.0], [1.0, 3.0]], (2, 2))
    """
    parts = low_rank_parts(cov)
    if parts is None:
        cov = pt.as_tensor_variable(cov)
        if diagonal is not None:
            cov = cov + pt.diag(diagonal * pt.ones(cov.shape[0]))
        return cov if factor is None else cov + pt.dot(factor, pt.transpose(factor))
    d, F = parts
    if diagonal is not None:
        d = d + diagonal
    if factor is not None:
        F = pt.concatenate([F, pt.as_tensor_variable(factor)], axis=1)
    return low_rank_covariance(d, F)


def _capacitance(d: Any, F: Any) -> tuple[pt.TensorVariable, pt.TensorVariable]:
    """``D⁻¹F`` and the lower Cholesky factor of ``I + Fᵀ D⁻¹ F`` (``k × k``)."""
    scaled = F / d[:, None]
    inner = pt.eye(F.shape[1]) + pt.dot(pt.transpose(F), scaled)
    return scaled, pt.linalg.cholesky(inner, lower=True)


def _woodbury_parts(
    r: np.ndarray, d: np.ndarray, F: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """``(log p, C⁻¹ r, diag C⁻¹, C⁻¹ F)`` of :class:`WoodburyLogDensity` with numpy/LAPACK."""
    n, k = F.shape
    if not np.all(d > 0):
        return -np.inf, np.zeros(n), np.zeros(n), np.zeros((n, k))
    scaled = F / d[:, None]
    chol, info = lapack.dpotrf(np.eye(k) + F.T @ scaled, lower=1, clean=1)
    if info != 0 or not np.all(np.isfinite(chol)):
        return -np.inf, np.zeros(n), np.zeros(n), np.zeros((n, k))
    b = scaled.T @ r
    c, _ = lapack.dtrtrs(chol, b, lower=1)
    inverse, _ = lapack.dpotri(chol, lower=1)
    inverse = np.tril(inverse) + np.tril(inverse, -1).T
    quad = float(np.sum(r**2 / d) - c @ c)
    log_det = float(np.sum(np.log(d)) + 2.0 * np.sum(np.log(np.diagonal(chol))))
    solved = scaled @ inverse  # C⁻¹ F = D⁻¹ F A⁻¹
    alpha = r / d - solved @ b
    diag_inverse = 1.0 / d - np.sum(solved * scaled, axis=1)
    return -0.5 * (quad + log_det + n * _LOG_2PI), alpha, diag_inverse, solved


class WoodburyLogDensity(Op):
    r"""``log N(r; 0, diag(d) + F Fᵀ)`` with ``C⁻¹ r``, ``diag C⁻¹`` and ``C⁻¹ F``, in ``O(n k²)``.

    With ``A = I_k + Fᵀ D⁻¹ F = L Lᵀ`` and ``c = L⁻¹ Fᵀ D⁻¹ r`` (Woodbury identity and
    matrix determinant lemma):

    .. math::

        r^\top C^{-1} r = r^\top D^{-1} r - c^\top c, \qquad
        \log|C| = \textstyle\sum_i \log d_i + 2 \sum_j \log L_{jj},

    and the gradient is written with the other three outputs (``α = C⁻¹ r``,
    ``C⁻¹ F = D⁻¹ F A⁻¹``): ``∂/∂r = -α``, ``∂/∂d = ½ (α² - diag C⁻¹)``,
    ``∂/∂F = α (αᵀ F) - C⁻¹ F``.  One op instead of PyTensor's Cholesky, triangular
    solves and their gradients: fewer nodes, and none of the ``AllocDiag`` graphs of the
    Cholesky gradient, whose late inlining (PyTensor 2.38) brought a second copy of
    everything upstream of ``F`` into a compiled gradient.  ``-inf`` when some
    ``d_i ≤ 0`` or ``A`` is not positive definite.  The gradient is defined for the
    first output.

    Examples
    --------
    >>> import numpy as np, pytensor.tensor as pt
    >>> from scipy.stats import multivariate_normal
    >>> d, F, r = np.array([1.0, 2.0, 0.5]), np.array([[1.0], [0.5], [2.0]]), np.ones(3)
    >>> logp = WoodburyLogDensity()(pt.as_tensor(r), pt.as_tensor(d), pt.as_tensor(F))[0]
    >>> dense = multivariate_normal(np.zeros(3), np.diag(d) + F @ F.T).logpdf(r)
    >>> bool(np.isclose(logp.eval(), dense))
    True
    """

    __props__ = ()

    def make_node(self, r, d, F):  # noqa: D102
        r, d, F = (pt.as_tensor_variable(a).astype("float64") for a in (r, d, F))
        if r.ndim != 1 or d.ndim != 1 or F.ndim != 2:
            raise ValueError("WoodburyLogDensity needs vectors r, d and a matrix F")
        return Apply(self, [r, d, F], [pt.dscalar(), pt.dvector(), pt.dvector(), pt.dmatrix()])

    def perform(self, node, inputs, outputs):  # noqa: D102
        logp, alpha, diag_inverse, solved = _woodbury_parts(*inputs)
        outputs[0][0] = np.array(logp)
        outputs[1][0] = alpha
        outputs[2][0] = diag_inverse
        outputs[3][0] = solved

    def L_op(self, inputs, outputs, output_grads):  # noqa: D102
        g_logp, *others = output_grads
        for g in others:
            if not isinstance(g.type, DisconnectedType):
                raise NotImplementedError("WoodburyLogDensity: gradient of outputs 1-3")
        _, _, F = inputs
        _, alpha, diag_inverse, solved = outputs
        g_F = pt.outer(alpha, pt.dot(alpha, F)) - solved
        return [-g_logp * alpha, 0.5 * g_logp * (alpha**2 - diag_inverse), g_logp * g_F]

    def connection_pattern(self, node):  # noqa: D102
        return [[True] * 4] * 3

    def infer_shape(self, fgraph, node, shapes):  # noqa: D102
        n, k = shapes[2]
        return [(), (n,), (n,), (n, k)]


_woodbury_log_density = WoodburyLogDensity()


def _capacitance_loops(r, d, F):
    """``(A = I + Fᵀ D⁻¹ F`` (lower triangle), ``b = Fᵀ D⁻¹ r``, ``rᵀ D⁻¹ r``, ``Σ log d)``."""
    n, k = F.shape
    inner, b = np.eye(k), np.zeros(k)
    quad, log_d = 0.0, 0.0
    for i in range(n):
        inv_d = 1.0 / d[i]
        quad += r[i] * r[i] * inv_d
        log_d += np.log(d[i])
        for a in range(k):
            fa = F[i, a] * inv_d
            b[a] += fa * r[i]
            for c in range(a + 1):
                inner[a, c] += fa * F[i, c]
    return inner, b, quad, log_d


def _small_cholesky(inner):
    """Lower Cholesky factor of the ``k × k`` ``inner`` (lower triangle read); NaN if not PD."""
    k = inner.shape[0]
    chol = np.zeros((k, k))
    for a in range(k):
        s = inner[a, a]
        for c in range(a):
            s -= chol[a, c] * chol[a, c]
        if not s > 0.0:
            chol[:, :] = np.nan
            return chol
        chol[a, a] = np.sqrt(s)
        for e in range(a + 1, k):
            t = inner[e, a]
            for c in range(a):
                t -= chol[e, c] * chol[a, c]
            chol[e, a] = t / chol[a, a]
    return chol


def _cholesky_inverse(chol):
    """``A⁻¹ = L⁻ᵀ L⁻¹`` from the lower factor ``L`` (full symmetric matrix)."""
    k = chol.shape[0]
    linv = np.zeros((k, k))
    for a in range(k):
        linv[a, a] = 1.0 / chol[a, a]
        for e in range(a + 1, k):
            s = 0.0
            for c in range(a, e):
                s -= chol[e, c] * linv[c, a]
            linv[e, a] = s / chol[e, e]
    inverse = np.empty((k, k))
    for a in range(k):
        for c in range(a + 1):
            s = 0.0
            for e in range(a, k):
                s += linv[e, a] * linv[e, c]
            inverse[a, c] = s
            inverse[c, a] = s
    return inverse


def _woodbury_numba_kernel(njit: Any) -> Any:
    """The jitted value-and-parts kernel of :class:`WoodburyLogDensity`, built with ``njit``."""
    capacitance = njit(_capacitance_loops)
    small_cholesky = njit(_small_cholesky)
    cholesky_inverse = njit(_cholesky_inverse)

    @njit
    def woodbury_log_density(r, d, F):
        # loops over the rows (n k²) and the k × k algebra in place: for k ≪ n the
        # LAPACK and BLAS calls of the matrix form cost more than the arithmetic
        n, k = F.shape
        failed = (np.array(-np.inf), np.zeros(n), np.zeros(n), np.zeros((n, k)))
        for i in range(n):
            if not d[i] > 0:
                return failed
        inner, b, quad, log_det = capacitance(r, d, F)
        chol = small_cholesky(inner)
        if not np.all(np.isfinite(chol)):
            return failed
        c = np.empty(k)  # forward substitution, L c = b
        for a in range(k):
            s = b[a]
            for e in range(a):
                s -= chol[a, e] * c[e]
            c[a] = s / chol[a, a]
            quad -= c[a] * c[a]
            log_det += 2.0 * np.log(chol[a, a])
        inverse = cholesky_inverse(chol)
        alpha, diag_inverse, solved = np.empty(n), np.empty(n), np.empty((n, k))
        for i in range(n):
            inv_d = 1.0 / d[i]
            mean_part, diag_part = 0.0, 0.0
            for a in range(k):
                s = 0.0
                for e in range(k):
                    s += F[i, e] * inverse[e, a]
                s *= inv_d
                solved[i, a] = s
                mean_part += s * b[a]
                diag_part += s * F[i, a]
            alpha[i] = r[i] * inv_d - mean_part
            diag_inverse[i] = inv_d - diag_part * inv_d
        logp = -0.5 * (quad + log_det + n * _LOG_2PI)
        return np.array(logp), alpha, diag_inverse, solved

    return woodbury_log_density


def _register_woodbury_numba() -> None:
    """Compile :class:`WoodburyLogDensity` natively in PyTensor's NUMBA mode (and nutpie)."""
    parts = _numba_dispatch()
    if parts is None:  # pragma: no cover - numba is a PyTensor dependency here
        return
    numba_basic, register_funcify_default_op_cache_key, _ = parts
    kernel = _woodbury_numba_kernel(numba_basic.numba_njit)

    @register_funcify_default_op_cache_key(WoodburyLogDensity)
    def _numba_woodbury_log_density(op, node, **kwargs):
        return kernel, 2  # the cache key salt: 2 since the loops


_register_woodbury_numba()


def woodbury_log_density(r: Any, diagonal: Any, factor: Any) -> pt.TensorVariable:
    r"""``log N(r; 0, diag(d) + F Fᵀ)`` in ``O(n k²)`` (Woodbury and determinant lemma).

    Through :class:`WoodburyLogDensity` (one op, its gradient in closed form);
    ``-inf`` when some ``d_i ≤ 0``.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.stats import multivariate_normal
    >>> d, F, r = np.array([1.0, 2.0, 0.5]), np.array([[1.0], [0.5], [2.0]]), np.ones(3)
    >>> logp = woodbury_log_density(r, d, F).eval()
    >>> bool(np.isclose(logp, multivariate_normal(np.zeros(3), np.diag(d) + F @ F.T).logpdf(r)))
    True
    """
    outputs = cast(list[pt.TensorVariable], _woodbury_log_density(r, diagonal, factor))
    return outputs[0]


def covariance_solve(cov: Any, rhs: Any) -> pt.TensorVariable:
    """``cov⁻¹ rhs`` (vector or matrix); by the Woodbury identity when ``cov`` is low-rank.

    Examples
    --------
    >>> import numpy as np
    >>> C = low_rank_covariance(np.array([1.0, 2.0]), np.array([[1.0], [1.0]]))
    >>> bool(np.allclose(C.eval() @ covariance_solve(C, np.ones(2)).eval(), 1.0))
    True
    """
    rhs = pt.as_tensor_variable(rhs)
    parts = low_rank_parts(cov)
    if parts is None:
        chol = pt.linalg.cholesky(cov, lower=True)
        return pt.linalg.cho_solve((chol, True), rhs)
    d, F = parts
    scaled, chol = _capacitance(d, F)
    inv_d = 1.0 / d if rhs.ndim == 1 else (1.0 / d)[:, None]
    inner = pt.linalg.cho_solve((chol, True), pt.dot(pt.transpose(scaled), rhs))
    return rhs * inv_d - pt.dot(scaled, inner)


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


def _pays(d: pt.TensorVariable, F: pt.TensorVariable) -> bool:
    """Whether the Woodbury form is the cheaper one: ``k < n`` (when the shapes are known)."""
    n, k = d.type.shape[0], F.type.shape[1]
    return n is None or k is None or k < n


class _GaussianLikelihoodRV(MvNormalRV):
    """``MvNormalRV`` whose log density is :func:`gaussian_log_density`."""


class GaussianLikelihood(pm.MvNormal):
    """:class:`pymc.MvNormal` (``mu``, ``cov``) with the one-pass log density above.

    Use for observed vectors; draws are those of ``MvNormal``.  A ``cov`` built by
    :func:`low_rank_covariance` (rank below ``n``) is evaluated by
    :func:`woodbury_log_density`.

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
        parts = low_rank_parts(cov)
        if parts is not None and _pays(*parts):
            return woodbury_log_density(value - mu, *parts)
        return gaussian_log_density(value, mu, cov)
