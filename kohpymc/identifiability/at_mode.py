"""The Taylor check at a point the data choose (the posterior mode), and its verdict in words.

At the prior centre a nonlinear model may be locally flat in parameters that the data
inform well near the fit (a threshold beyond the data, a rate so fast that its transient
is over before the first measurement).  :func:`check_at_point` runs the same check,
:func:`~kohpymc.identifiability.model_check.model_taylor_check`, at any point of the
user's parameters; when a confounded set there holds physics parameters only, the
physics-alone check (:func:`~kohpymc.identifiability.physics_check.taylor_check`) repeats
it on a denser design to tell a structural deficit from a practical one
(:func:`~kohpymc.identifiability.model_check.mark_structural`).
:func:`ridge_text` says what the report found: the confounded combinations, or the
weakly informed direction of a full-rank but ill-conditioned sensitivity matrix.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from kohpymc.identifiability.model_check import mark_structural, model_taylor_check
from kohpymc.identifiability.rank import RTOL, IdentifiabilityReport

__all__ = ["check_at_point", "ridge_text"]


def check_at_point(
    built: Any,
    point: Mapping[str, Any],
    *,
    physics: Any = None,
    inputs: Mapping[str, Any] | None = None,
    rtol: float = RTOL,
) -> IdentifiabilityReport:
    """The Taylor check of a built (unmarginalized) formulation at ``point``.

    Parameters
    ----------
    built : CalibrationModel
        ``compose_model(..., marginalize=False)``.
    point : mapping
        Parameter name -> value in the user's units (e.g. the posterior mode); names
        not given stay at the prior centre.
    physics : PhysicsModel, optional
        With ``inputs``: when a confounded set holds physics parameters only, the check
        of the physics alone is repeated on a denser design and ``structural`` is set
        (:func:`~kohpymc.identifiability.model_check.mark_structural`).
    inputs : mapping, optional
        The data design (input name -> values).
    rtol : float
        Relative singular-value tolerance.

    Returns
    -------
    IdentifiabilityReport

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc import CalibrationData, PhysicsModel, Uniform
    >>> from kohpymc.model import compose_model
    >>> x = np.linspace(0.5, 2.0, 8)
    >>> physics = PhysicsModel(lambda i, p: p["a"] * p["b"] * i["x"],
    ...                        {"a": Uniform(0.1, 10.0), "b": Uniform(0.1, 10.0)}, inputs=["x"])
    >>> built = compose_model(physics, CalibrationData({"x": x}, 3 * x, noise_sd=0.1),
    ...                       marginalize=False)
    >>> report = check_at_point(built, {"a": 1.5, "b": 2.0}, physics=physics,
    ...                         inputs={"x": x})
    >>> report.rank, report.structural
    (1, True)
    """
    report = model_taylor_check(built, point=point, rtol=rtol)
    if physics is None or inputs is None:
        return report
    return mark_structural(report, physics, inputs, rtol=rtol)


def ridge_text(report: IdentifiabilityReport) -> str:
    """What the report found, in words: confounded or weakly informed combinations.

    Empty when the sensitivity matrix has full rank and is well conditioned.

    Examples
    --------
    >>> import numpy as np
    >>> from kohpymc.identifiability import analyse_matrix
    >>> x = np.linspace(1.0, 2.0, 5)
    >>> ridge_text(analyse_matrix(np.column_stack([x, 2 * x]), ["a", "b"]))[:31]
    'a and b are confounded: changin'
    >>> ridge_text(analyse_matrix(np.column_stack([x, x**2]), ["a", "b"]))
    ''
    """
    if report.identifiable:
        return report.weakly_informed()
    text = "; ".join(report.confounded())
    if report.structural is True:
        text += " (the deficit persists on a denser design: structural)"
    elif report.structural is False:
        text += " (the deficit disappears on a denser design: practical, more data would help)"
    return text
