"""Compiled inner loops of the semi-analytic solution (numba, a PyTensor dependency).

The right-hand side and its pieces are scalar functions of one setting's coefficients;
the kernels loop over settings, quadrature nodes and rows with them, so one formula
serves the steady state, the grid, the rows and the sensitivities (see
:mod:`kohpymc.examples.dielectric.kinetics` and the package docstring, Numerics).
Settings are independent: a setting's result does not depend on the others solved
with it.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from kohpymc.examples.dielectric.constants import _FEEDBACK, _Q, THICKNESS

#: 1 / (q d): trapping rate per injected current density, m⁻³ s⁻¹ per A/m²
_SCALE = 1.0 / (_Q * THICKNESS)
_LOG_QD = math.log(_Q * THICKNESS)
_N_TINY = 1e-250  # m^-3: trapped densities below this are treated as zero

_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


@_jit
def rhs(n, E_app, a, b, N_T, kappa, e):
    """``f(n)``, ``f'(n)``, ``J_FN(E_inj)`` and the capture probability ``P_c(n)``."""
    E = max(E_app - _FEEDBACK * n, 1.0)  # J_FN(1 V/m) = 0 in floating point
    J = a * E**2 * math.exp(-b / E)
    dJ = -_FEEDBACK * J * (2.0 / E + b / E**2)
    capture = -math.expm1(-kappa * (N_T - n))
    dcapture = -kappa * (1.0 - capture)
    f = _SCALE * J * capture - e * n
    fp = _SCALE * (dJ * capture + J * dcapture) - e
    return f, fp, J, capture


@_jit
def bases_given(n, J, capture, E_app, b, N_T, kappa, e):
    """The five ``φ_k(n)`` of ``∂f/∂θ`` given ``J_FN`` and ``P_c`` at ``n``."""
    E = max(E_app - _FEEDBACK * n, 1.0)
    phi_a = _SCALE * J * capture
    phi_c = _SCALE * J * kappa * math.exp(-kappa * (N_T - n))
    return phi_a, phi_a * b / E, phi_c, phi_c * n, -e * n


@_jit
def bases(n, E_app, a, b, N_T, kappa, e):
    """The five ``φ_k(n)`` of ``∂f/∂θ`` and ``J_FN(E_inj)``."""
    _, _, J, capture = rhs(n, E_app, a, b, N_T, kappa, e)
    return bases_given(n, J, capture, E_app, b, N_T, kappa, e), J


@_jit
def log_balance(n, E_app, a, b, N_T, kappa, log_e):
    """``ln(J_FN P_c / (q d)) - ln e`` and its ``d/dn`` (without the ``-ln n`` term)."""
    E = E_app - _FEEDBACK * n
    z = kappa * (N_T - n)
    h = math.log(a) + 2.0 * np.log(E) - b / E + np.log(-math.expm1(-z)) - _LOG_QD - log_e
    slope = -_FEEDBACK * (2.0 / E + b / E**2) - kappa / math.expm1(z)
    return h, slope


@_jit
def rhs_array(n, rows, E_app, a, b, N_T, kappa, e):
    """:func:`rhs` (first three) at ``n`` ``(R, K)``; row r of n in setting ``rows[r]``."""
    f, fp, J = np.empty_like(n), np.empty_like(n), np.empty_like(n)
    for r in range(n.shape[0]):
        i = rows[r]
        for k in range(n.shape[1]):
            f[r, k], fp[r, k], J[r, k], _ = rhs(
                n[r, k], E_app[i], a[i], b[i], N_T[i], kappa[i], e[i]
            )
    return f, fp, J


@_jit
def bases_array(n, rows, E_app, a, b, N_T, kappa, e):
    """:func:`bases` at ``n`` ``(R, K)`` (settings ``rows``): ``(5, R, K)`` and ``J`` ``(R, K)``."""
    phis, J = np.empty((5,) + n.shape), np.empty_like(n)
    for r in range(n.shape[0]):
        i = rows[r]
        for k in range(n.shape[1]):
            values, J[r, k] = bases(n[r, k], E_app[i], a[i], b[i], N_T[i], kappa[i], e[i])
            for m in range(5):
                phis[m, r, k] = values[m]
    return phis, J


@_jit
def combine(C, rows, w):
    """``Σ_k C[rows[r], i, k] w[k, r]``: ``(R, P)`` from ``C`` ``(G, P, M)``, ``w`` ``(M, R)``."""
    out = np.zeros((rows.size, C.shape[1]))
    for r in range(rows.size):
        for i in range(C.shape[1]):
            for k in range(C.shape[2]):
                out[r, i] += C[rows[r], i, k] * w[k, r]
    return out


@_jit
def steady_state(E_app, a, b, N_T, kappa, log_e, n_max, max_iter):
    """Root ``n_ss`` of f per setting (0 without injection); see ``kinetics._steady_state``."""
    out = np.zeros(E_app.size)
    log_tiny = math.log(_N_TINY)
    for i in range(E_app.size):
        if not E_app[i] > 0:
            continue
        coef = (E_app[i], a[i], b[i], N_T[i], kappa[i], log_e[i])
        h0, _ = log_balance(1e-300, *coef)
        log_max = np.log(n_max[i])
        singular_top = log_max <= h0
        log_top = log_max if singular_top else h0
        if not log_top > log_tiny:  # n_ss <= top < 1e-250 m^-3: no injection
            continue
        top = math.exp(log_top)
        x = log_top - math.log(2.0)
        for _ in range(max_iter):
            n = math.exp(x)
            h, slope = log_balance(n, *coef)
            new = x - (h - np.log(n)) / (n * slope - 1.0)
            if not np.isfinite(new) or new >= log_top:
                new = np.log(0.5 * (n + top)) if singular_top else log_top
            done = abs(new - x) <= 1e-14 * max(1.0, abs(x))
            x = new
            if done:
                break
        out[i] = math.exp(x)
    return out


#: nodes computed past the first node later than a setting's last row: the rows'
#: cubic pieces end at or before that node, and the sensitivity integrals' slope there
#: is a central difference (results equal those of the whole grid)
_EXTRA_NODES = 2


@_jit
def grid_solution(n_ss, E_app, a, b, N_T, kappa, e, U, H, t_rows, inv):
    """``t(s)`` on the grid ``n = n_ss expit(s)`` of every setting, as far as its rows need.

    Returns ``t``, ``g = dt/ds``, ``f``, ``J_FN``, ``P_c`` at the nodes ``(G, K)``,
    ``f(0)`` ``(G,)`` and the number of nodes computed per setting ``(G,)``: up to
    ``_EXTRA_NODES`` past the first node later than the setting's last row time
    (``t = inf`` beyond).  Settings without charge (``n_ss <= 1e-250``) get the grid of
    ``n_ss = 1`` with ``f = 1``, ``f' = 0`` (finite, later masked).
    """
    G, K = n_ss.size, U.size
    t_last = np.full(G, -np.inf)
    for r in range(t_rows.size):
        t_last[inv[r]] = max(t_last[inv[r]], t_rows[r])
    t, g, f = np.full((G, K), np.inf), np.empty((G, K)), np.empty((G, K))
    J, capture = np.empty((G, K)), np.empty((G, K))
    f0 = np.ones(G)
    used = np.full(G, K)
    for i in range(G):
        live = n_ss[i] > _N_TINY
        safe = n_ss[i] if live else 1.0
        coef = (E_app[i], a[i], b[i], N_T[i], kappa[i], e[i])
        if live:
            f0[i] = rhs(0.0, *coef)[0]
        acc, g_prev, dg_prev, t_first = 0.0, 0.0, 0.0, 0.0
        for k in range(K):
            n = safe * U[k]
            f_k, fp_k, J[i, k], capture[i, k] = rhs(n, *coef)
            if not live:
                f_k, fp_k = 1.0, 0.0
            g_k = n * (1.0 - U[k]) / f_k
            dg_k = g_k * (1.0 - 2.0 * U[k]) - g_k**2 * fp_k
            if k == 0:
                t_first = 0.5 * n * (1.0 / f0[i] + 1.0 / f_k)
            else:
                acc += 0.5 * H * (g_k + g_prev) + H**2 / 12.0 * (dg_prev - dg_k)
            t[i, k] = t_first + acc
            f[i, k], g[i, k] = f_k, g_k
            g_prev, dg_prev = g_k, dg_k
            if t[i, k] > t_last[i] and used[i] == K:
                used[i] = min(k + 1 + _EXTRA_NODES, K)
            if k + 1 >= used[i]:
                break
    return t, g, f, J, capture, f0, used


@_jit
def _last_at_or_before(values, x):
    """Index of the last of the sorted ``values`` that is ``<= x`` (-1: none)."""
    lo, hi = 0, values.size
    while lo < hi:
        mid = (lo + hi) // 2
        if values[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


@_jit
def _hermite(x, y0, d0, y1, d1):
    """Cubic Hermite on [0, 1] with values ``y`` and (scaled) slopes ``d``."""
    x2, x3 = x * x, x * x * x
    return (
        (2 * x3 - 3 * x2 + 1) * y0
        + (x3 - 2 * x2 + x) * d0
        + (3 * x2 - 2 * x3) * y1
        + (x3 - x2) * d1
    )


@_jit
def interpolate_rows(t_rows, inv, t_grid, g, f, f0, n_ss, rate_ss, S, U):
    """``n`` at each row's time from its setting's grid.

    Returns ``n``, the node index ``j`` (last node at or before t; -1 before the first,
    ``K - 1`` after the last) and ``s`` (interpolated grid coordinate).  Between nodes
    cubic Hermite in ``s(t)`` (slopes ``1/g``), before the first node a cubic from
    ``n(0) = 0`` (slopes ``f(0)``, ``f(n_first)``), after the last the linear relaxation.
    """
    last = S.size - 1
    rows = t_rows.size
    n, s, j = np.empty(rows), np.empty(rows), np.empty(rows, dtype=np.intp)
    for r in range(rows):
        i, t = inv[r], t_rows[r]
        jr = _last_at_or_before(t_grid[i], t)
        jc = min(max(jr, 0), last - 1)
        t0, t1 = t_grid[i, jc], t_grid[i, jc + 1]
        width = t1 - t0
        x = min(max((t - t0) / width, 0.0), 1.0)
        s[r] = _hermite(x, S[jc], width / g[i, jc], S[jc + 1], width / g[i, jc + 1])
        j[r] = jr
        if not n_ss[i] > _N_TINY:
            n[r] = 0.0
        elif jr < 0:
            tf = t_grid[i, 0]
            d0, d1 = f0[i] * tf, f[i, 0] * tf
            n[r] = _hermite(t / tf, 0.0, d0, n_ss[i] * U[0], d1)
        elif jr >= last:
            gap = (1.0 - U[last]) * math.exp(-rate_ss[i] * (t - t_grid[i, last]))
            n[r] = n_ss[i] * (1.0 - gap)
        else:
            n[r] = n_ss[i] / (1.0 + math.exp(-s[r]))
    return n, j, s


@_jit
def charge_integrals(safe, used, g, f, J, capture, f0, phis0, E_app, b, N_T, kappa, e, U, H):
    """``Q_k(s) = ∫ φ_k g / f ds`` (k = B..E) at the nodes, and the integrands ``q_k``.

    Returns ``Q`` and ``q``, both ``(4, G, K)``: the Euler–Maclaurin-corrected
    cumulative trapezoid from the first node (slopes of ``q`` by second-order
    differences) plus the trapezoid in n from 0 to the first node, with ``φ(0)``
    (``phis0``, ``(5, G)``) and ``f(0)`` (``f0``, ``(G,)``).  ``safe`` is ``n_ss``, or 1
    for settings without charge, and ``used`` the nodes computed (as in
    :func:`grid_solution`): ``Q`` up to the last but one of them unless all are used.
    """
    G, K = safe.size, U.size
    q, Q = np.empty((4, G, K)), np.empty((4, G, K))
    phis_first = np.empty(4)
    for i in range(G):
        coef = (E_app[i], b[i], N_T[i], kappa[i], e[i])
        for k in range(used[i]):
            n = safe[i] * U[k]
            phis = bases_given(n, J[i, k], capture[i, k], *coef)
            weight = g[i, k] / f[i, k]
            for m in range(4):
                q[m, i, k] = phis[m + 1] * weight
                if k == 0:
                    phis_first[m] = phis[m + 1]
        half_first = 0.5 * safe[i] * U[0]
        for m in range(4):
            qm = q[m, i]
            first = half_first * (phis0[m + 1, i] / f0[i] ** 2 + phis_first[m] / f[i, 0] ** 2)
            d_first = (-3.0 * qm[0] + 4.0 * qm[1] - qm[2]) / (2.0 * H)
            acc = 0.0
            Q[m, i, 0] = first
            for k in range(1, used[i] if used[i] == K else used[i] - 1):
                acc += 0.5 * H * (qm[k] + qm[k - 1])
                if k < K - 1:
                    dq = (qm[k + 1] - qm[k - 1]) / (2.0 * H)
                else:
                    dq = (3.0 * qm[k] - 4.0 * qm[k - 1] + qm[k - 2]) / (2.0 * H)
                Q[m, i, k] = first + acc + H**2 / 12.0 * (d_first - dq)
    return Q, q


@_jit
def integrals_at_rows(Q, q, inv, j, s, S, H):
    """Cubic Hermite in ``s`` of the four ``Q_k`` at each row (slopes ``q``): ``(4, rows)``."""
    last = S.size - 1
    out = np.empty((4, inv.size))
    for r in range(inv.size):
        i, jc = inv[r], min(max(j[r], 0), last - 1)
        x = (s[r] - S[jc]) / H
        for m in range(4):
            out[m, r] = _hermite(
                x, Q[m, i, jc], H * q[m, i, jc], Q[m, i, jc + 1], H * q[m, i, jc + 1]
            )
    return out
