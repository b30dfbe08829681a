r"""Several GPs' cross-covariances and predictive-variance terms ``kᵀ K⁻¹ k`` as one op.

A GP emulator's predictive covariance at test rows with cross-covariances ``k`` to its
``N`` training runs is ``prior - kᵀ K⁻¹ k``.  With the inverse Cholesky factor
``L⁻¹`` of ``K`` stored once, ``V = L⁻¹ kᵀ`` and ``kᵀ K⁻¹ k = Vᵀ V`` (the stable form:
a sum of squares).  Written as PyTensor graph ops that is a dense batched product with
``L⁻¹`` forward and another with ``L⁻ᵀ`` in the gradient, each over the full ``N × N``
matrix although half of it is zero.  :class:`KernelQuadratic` computes, for ``K`` GPs
at once, at a point ``u`` (``p`` coordinates) with training coordinates ``U``
``(N, p)``, length scales ``ℓ`` ``(K, p)`` and a fixed part ``r₀²`` ``(K, m, N)`` of the
squared distances of ``m`` test rows (their scalar inputs),

.. math::

    r²_{kaj} = r₀²_{kaj} + \textstyle\sum_l ((U_{jl} - u_l) / ℓ_{kl})², \qquad
    k = κ(r²), \qquad Q_k = V_kᵀ V_k, \qquad V_k = L_k^{-1} k_kᵀ, \qquad
    W_k = K_k^{-1} k_kᵀ = L_k^{-ᵀ} V_k,

touching only the lower triangle of every ``L⁻¹`` (``N²`` multiply-adds per GP and
test row), with ``κ`` the kernel of :mod:`kohpymc.emulator.gp` (squared exponential
or Matérn 5/2, amplitude ``s²``).  Its gradient is written with ``W`` (no further pass
over ``L⁻¹``):

.. math::

    \partial \ell / \partial k_{k,a} = G^k_{k,a} + \textstyle\sum_b (G_{k,ab} + G_{k,ba}) W_{k,b},
    \qquad \partial \ell / \partial r² = (\partial \ell / \partial k)\, κ'(r²),

with ``G^k`` and ``G`` the gradients of ``k`` and ``Q``, then through ``r²`` to ``u``
and ``r₀²``.  The training data (``L⁻¹``, ``U``, ``ℓ``, ``s²``) are inputs, not
constants of the op, so that a compiled graph does not embed (and a numba cache key
does not depend on) them: pass them as shared variables.  No gradient flows to them.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import pytensor.tensor as pt
from pytensor.gradient import DisconnectedType
from pytensor.graph.basic import Apply
from pytensor.graph.op import Op

__all__ = ["KernelQuadratic", "kernel_quadratic"]

_SQRT5 = float(np.sqrt(5.0))
_KERNELS = ("se", "matern52")


def kernel_values(kernel: str, r2: Any, amp: Any, lib: Any = np) -> Any:
    """``κ(r²)``: ``s² exp(-r²/2)`` or ``s² (1 + √5 r + 5 r²/3) exp(-√5 r)``.

    ``amp`` broadcasts against ``r2``; Matérn's ``r = √(r² + 1e-12)`` keeps its
    gradient finite at zero distance.

    Examples
    --------
    >>> float(kernel_values("se", np.array(0.0), 2.0))
    2.0
    """
    if kernel == "se":
        return amp * lib.exp(-0.5 * r2)
    r = lib.sqrt(r2 + 1e-12)
    return amp * (1.0 + _SQRT5 * r + 5.0 * r2 / 3.0) * lib.exp(-_SQRT5 * r)


def _kernel_slope(kernel: str, r2: Any, amp: Any, values: Any) -> Any:
    """``dκ/dr²`` (PyTensor) of :func:`kernel_values`, given its ``values``."""
    if kernel == "se":
        return -0.5 * values
    r = pt.sqrt(r2 + 1e-12)
    return amp * pt.exp(-_SQRT5 * r) * (-5.0 / 6.0 - (5.0 * _SQRT5 / 6.0) * r2 / r)


def _squared_distances(U: Any, lengthscales: Any, base: Any, u: Any, lib: Any = np) -> Any:
    """``r²`` ``(K, m, N)``: ``r₀²`` plus the scaled squared distances of ``u`` to ``U``."""
    diff = (U[None, :, :] - u[None, None, :]) / lengthscales[:, None, :]  # (K, N, p)
    return base + lib.sum(diff**2, axis=-1)[:, None, :]


def _quadratic_numpy(
    kernel: str, chol_inv: np.ndarray, U: np.ndarray, lengthscales: np.ndarray,
    amp: np.ndarray, base: np.ndarray, u: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``(k, Q, W, r²)`` of :class:`KernelQuadratic` with numpy (dense products)."""
    r2 = _squared_distances(U, lengthscales, base, u)
    kc = kernel_values(kernel, r2, amp[:, None, None])
    lower = np.tril(chol_inv)
    V = np.matmul(lower, np.swapaxes(kc, 1, 2))  # (K, N, m)
    Q = np.matmul(np.swapaxes(V, 1, 2), V)
    W = np.swapaxes(np.matmul(np.swapaxes(lower, 1, 2), V), 1, 2)
    return kc, Q, W, r2


class KernelQuadratic(Op):
    """``(k, Q, W, r²)``: ``K`` GPs' kernel values, ``k K⁻¹ kᵀ``, ``k K⁻¹`` and distances.

    Parameters
    ----------
    kernel : {"se", "matern52"}

    Inputs: ``chol_inv`` ``(K, N, N)``, lower-triangular inverse Cholesky factors of
    the training covariances (the upper triangle is never read); ``U`` ``(N, p)``,
    the training coordinates; ``lengthscales`` ``(K, p)``; ``amp`` ``(K,)``, the kernel
    amplitudes; ``base`` ``(K, m, N)``, the fixed part of the squared distances of the
    ``m`` test rows; ``u`` ``(p,)``, the point.  Outputs: ``k`` ``(K, m, N)``, ``Q``
    ``(K, m, m)``, ``W`` ``(K, m, N)`` and ``r²`` ``(K, m, N)``.  The gradient is
    defined for ``k``, ``Q`` and ``r²`` with respect to ``u`` and ``base``.

    Examples
    --------
    >>> import numpy as np
    >>> U = np.array([[0.0], [1.0]])
    >>> K = np.exp(-0.5 * (U - U.T) ** 2) + 1e-6 * np.eye(2)
    >>> chol_inv = np.linalg.inv(np.linalg.cholesky(K))[None]
    >>> kc, Q, W, r2 = kernel_quadratic("se", chol_inv, U, np.ones((1, 1)), np.ones(1),
    ...                                 np.zeros((1, 1, 2)), np.array([0.4]))
    >>> k = np.exp(-0.5 * (U[:, 0] - 0.4) ** 2)
    >>> bool(np.isclose(Q.eval()[0, 0, 0], k @ np.linalg.solve(K, k)))
    True
    """

    __props__ = ("kernel",)

    def __init__(self, kernel: str) -> None:
        if kernel not in _KERNELS:
            raise ValueError(f"kernel must be one of {list(_KERNELS)}, got {kernel!r}")
        self.kernel = kernel

    def make_node(self, chol_inv, U, lengthscales, amp, base, u):  # noqa: D102
        inputs = [
            pt.as_tensor_variable(a).astype("float64")
            for a in (chol_inv, U, lengthscales, amp, base, u)
        ]
        if [a.ndim for a in inputs] != [3, 2, 2, 1, 3, 1]:
            raise ValueError(
                "KernelQuadratic needs chol_inv (K, N, N), U (N, p), lengthscales (K, p), "
                "amp (K,), base (K, m, N) and u (p,)"
            )
        K, m, N = inputs[4].type.shape
        shapes = ((K, m, N), (K, m, m), (K, m, N), (K, m, N))
        return Apply(self, inputs, [pt.tensor(dtype="float64", shape=s) for s in shapes])

    def perform(self, node, inputs, outputs):  # noqa: D102
        for slot, value in zip(outputs, _quadratic_numpy(self.kernel, *inputs), strict=True):
            slot[0] = value

    def L_op(self, inputs, outputs, output_grads):  # noqa: D102
        _, U, lengthscales, amp, _, u = inputs
        kc, _, W, r2 = outputs
        g_kc, g_q, g_w, g_r2 = output_grads
        if not isinstance(g_w.type, DisconnectedType):
            raise NotImplementedError("KernelQuadratic: gradient of W")
        total = pt.zeros_like(kc) if isinstance(g_kc.type, DisconnectedType) else g_kc
        if not isinstance(g_q.type, DisconnectedType):
            total = total + pt.matmul(g_q + g_q.transpose(0, 2, 1), W)
        g_dist = total * _kernel_slope(self.kernel, r2, amp[:, None, None], kc)
        if not isinstance(g_r2.type, DisconnectedType):
            g_dist = g_dist + g_r2
        per_run = pt.sum(g_dist, axis=1)  # (K, N)
        diff = (U[None, :, :] - u[None, None, :]) / lengthscales[:, None, :] ** 2  # (K, N, p)
        g_u = -2.0 * pt.sum(per_run[:, :, None] * diff, axis=(0, 1))
        disconnected = [DisconnectedType()() for _ in range(4)]
        return [*disconnected, g_dist, g_u]

    def connection_pattern(self, node):  # noqa: D102
        return [[False] * 4] * 4 + [[True] * 4] * 2

    def infer_shape(self, fgraph, node, shapes):  # noqa: D102
        K, m, N = shapes[4]
        return [(K, m, N), (K, m, m), (K, m, N), (K, m, N)]


def kernel_quadratic(
    kernel: str, chol_inv: Any, U: Any, lengthscales: Any, amp: Any, base: Any, u: Any
) -> tuple[pt.TensorVariable, pt.TensorVariable, pt.TensorVariable, pt.TensorVariable]:
    """``(k, Q, W, r²)`` of :class:`KernelQuadratic` as PyTensor variables.

    Examples
    --------
    See :class:`KernelQuadratic`.
    """
    outputs = cast(
        list[pt.TensorVariable], KernelQuadratic(kernel)(chol_inv, U, lengthscales, amp, base, u)
    )
    kc, Q, W, r2 = outputs
    return kc, Q, W, r2


def _register_numba() -> None:
    """Compile :class:`KernelQuadratic` natively in PyTensor's NUMBA mode (and nutpie)."""
    try:
        from pytensor.link.numba.dispatch import basic as numba_basic
        from pytensor.link.numba.dispatch.basic import register_funcify_default_op_cache_key
    except ImportError:  # pragma: no cover - numba is a PyTensor dependency here
        return

    @numba_basic.numba_njit
    def lower_both(chol_inv, k, kc, a, v, w):
        """``v = tril(L_k⁻¹) @ kc[k, a]`` and ``w = tril(L_k⁻¹)ᵀ @ v`` in one pass over the rows.

        Row ``i`` gives ``v_i`` (a dot product over its lower part) and is then added,
        times ``v_i``, to ``w`` while it is in cache: ``L⁻¹`` (~1.3 MB for 7 GPs on 150
        runs) is read once per evaluation instead of twice.  The sums run in the same
        order as two separate passes would.
        """
        w[:] = 0.0
        for i in range(chol_inv.shape[1]):
            s = 0.0
            for j in range(i + 1):
                s += chol_inv[k, i, j] * kc[k, a, j]
            v[i] = s
            for j in range(i + 1):
                w[j] += s * chol_inv[k, i, j]

    @register_funcify_default_op_cache_key(KernelQuadratic)
    def _numba_kernel_quadratic(op, node, **kwargs):
        se = op.kernel == "se"

        @numba_basic.numba_njit
        def kernel_quadratic(chol_inv, U, lengthscales, amp, base, u):
            K, m, N = base.shape
            p = u.shape[0]
            kc = np.empty((K, m, N))
            Q = np.empty((K, m, m))
            W = np.empty((K, m, N))
            r2 = np.empty((K, m, N))
            V = np.empty((m, N))
            for k in range(K):
                for j in range(N):
                    d2 = 0.0
                    for c in range(p):
                        z = (U[j, c] - u[c]) / lengthscales[k, c]
                        d2 += z * z
                    for a in range(m):
                        r2[k, a, j] = base[k, a, j] + d2
                for a in range(m):
                    for j in range(N):
                        if se:
                            kc[k, a, j] = amp[k] * np.exp(-0.5 * r2[k, a, j])
                        else:
                            r = np.sqrt(r2[k, a, j] + 1e-12)
                            poly = 1.0 + _SQRT5 * r + 5.0 * r2[k, a, j] / 3.0
                            kc[k, a, j] = amp[k] * poly * np.exp(-_SQRT5 * r)
                    lower_both(chol_inv, k, kc, a, V[a], W[k, a])
                for a in range(m):
                    for b in range(a + 1):
                        s = 0.0
                        for i in range(N):
                            s += V[a, i] * V[b, i]
                        Q[k, a, b] = s
                        Q[k, b, a] = s
            return kc, Q, W, r2

        return kernel_quadratic, 2  # the cache key salt: 2 since the one-pass products


_register_numba()
