r"""Finite-difference Jacobians ``∂G/∂θ`` of a numpy physics model.

* ``scheme="central"`` (default): ``J[:, j] = (G(θ + h_j e_j) - G(θ - h_j e_j)) / 2h_j``
  with ``h_j = ε^{1/3} · max(|θ_j|, s_j)``, ``ε`` the float64 machine epsilon
  (ε^{1/3} ≈ 6.1e-6) and ``s_j`` the prior's typical magnitude.  Truncation error is
  O(h²); cost is ``2p`` model evaluations per gradient.
* ``scheme="forward"``: ``(G(θ + h_j e_j) - G(θ)) / h_j`` with ``h_j = √ε · max(|θ_j|, s_j)``
  (√ε ≈ 1.5e-8); O(h) error, ``p + 1`` evaluations per gradient.

Using ``max(|θ_j|, s_j)`` keeps the step from collapsing when a parameter passes
through zero.  NUTS needs one gradient per leapfrog step, so a gradient costs
``2p`` (or ``p + 1``) times one model run: supply ``jacobian=`` when you can.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Literal

import numpy as np

__all__ = ["default_relative_step", "finite_difference_jacobian"]

_EPS = np.finfo(np.float64).eps


def default_relative_step(scheme: Literal["central", "forward"]) -> float:
    """Relative step ``ε^{1/3}`` (central) or ``√ε`` (forward).

    Examples
    --------
    >>> f"{default_relative_step('central'):.2e}", f"{default_relative_step('forward'):.2e}"
    ('6.06e-06', '1.49e-08')
    """
    return _EPS ** (1 / 3) if scheme == "central" else np.sqrt(_EPS)


def finite_difference_jacobian(
    function: Callable[[dict[str, float]], np.ndarray],
    params: Mapping[str, float],
    scales: Mapping[str, float],
    *,
    scheme: Literal["central", "forward"],
    relative_step: float,
) -> np.ndarray:
    """``∂G/∂θ`` by finite differences, shape ``(n, p)`` with columns in ``params`` order.

    Parameters
    ----------
    function : callable
        ``function(params) -> (n,) array``: the model at fixed inputs.
    params : mapping
        Parameter name -> value θ_j (the expansion point).
    scales : mapping
        Parameter name -> typical magnitude ``s_j``; the step is
        ``h_j = relative_step · max(|θ_j|, s_j)``.
    scheme : {"central", "forward"}
        Difference scheme (see the module docstring).
    relative_step : float
        Relative step (see :func:`default_relative_step`).

    Returns
    -------
    ndarray, shape (n, p)

    Examples
    --------
    >>> import numpy as np
    >>> t = np.array([0.0, 1.0])
    >>> J = finite_difference_jacobian(
    ...     lambda p: p["a"] * np.exp(-p["k"] * t), {"a": 2.0, "k": 0.5}, {"a": 1.0, "k": 1.0},
    ...     scheme="central", relative_step=default_relative_step("central"))
    >>> bool(np.allclose(J, [[1.0, 0.0], [np.exp(-0.5), -2.0 * np.exp(-0.5)]]))
    True
    """
    p = dict(params)
    cols = []
    base = function(p) if scheme == "forward" else None
    for name in p:
        h = relative_step * max(abs(p[name]), scales[name])
        up = dict(p)
        up[name] = p[name] + h
        f_up = function(up)
        if scheme == "central":
            down = dict(p)
            down[name] = p[name] - h
            cols.append((f_up - function(down)) / (2 * h))
        else:
            cols.append((f_up - base) / h)
    return np.column_stack(cols)
