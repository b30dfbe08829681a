"""Identifiability before sampling (paper Section 4, and its stated future work).

First-order Taylor check (Eqs. 15–16).  For ``G_new(x; ψ) = G(x; θ) + m(x; φ)`` with
``ψ = [θ, φ]`` the sensitivity matrix ``A[i, j] = ∂G_new/∂ψ_j`` at the data inputs and an
expansion point ``ψ̂`` decides local identifiability: rank ``r_A < p`` means the linearised
system has infinitely many solutions.

Numerical rank: see :mod:`kohpymc.identifiability.rank` (column scaling, the default
``rtol`` and why).

Beyond the paper:

* the null space of ``A`` names *which combination* is confounded (a direction in ψ
  along which the output does not change), and every minimal set of parameters that
  cannot be identified together (the circuits of the column matroid) is listed by a
  search restricted to the parameters touched by the null space — no ``p!`` permutations;
* structural vs practical: the check is repeated on a denser design; a deficit that
  persists is reported as structural;
* hyperparameters (:func:`fisher_information_check`): the expected Fisher information of
  the full Gaussian likelihood ``y ~ N(μ(ψ), Σ(ψ))`` of a formulation,
  ``I_ij = ∂_i μᵀ Σ⁻¹ ∂_j μ + ½ tr(Σ⁻¹ ∂_iΣ Σ⁻¹ ∂_jΣ)``, includes variance and GP
  covariance parameters; its rank and conditioning get the same treatment.

Layers:

* :mod:`~kohpymc.identifiability.rank`: the rank analysis of a matrix (pure numpy);
* :mod:`~kohpymc.identifiability.physics_check`: the Taylor check of physics models alone;
* :mod:`~kohpymc.identifiability.model_check`: the Taylor check of a formulation's PyMC
  model;
* :mod:`~kohpymc.identifiability.fisher`: the Fisher-information check of all parameters;
* :mod:`~kohpymc.identifiability.at_mode`: the check at a point the data choose (the
  posterior mode, which :func:`kohpymc.calibrate` finds before sampling) and its verdict
  in words.
"""

from kohpymc.identifiability.at_mode import check_at_point, ridge_text
from kohpymc.identifiability.fisher import fisher_information_check
from kohpymc.identifiability.model_check import check_formulation, model_taylor_check
from kohpymc.identifiability.physics_check import sensitivity_matrix, taylor_check
from kohpymc.identifiability.rank import (
    RTOL,
    IdentifiabilityReport,
    IdentifiabilityWarning,
    algorithm1,
    analyse_matrix,
)

__all__ = [
    "IdentifiabilityReport",
    "IdentifiabilityWarning",
    "analyse_matrix",
    "algorithm1",
    "sensitivity_matrix",
    "taylor_check",
    "check_formulation",
    "model_taylor_check",
    "fisher_information_check",
    "check_at_point",
    "ridge_text",
    "RTOL",
]
