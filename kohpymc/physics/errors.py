"""The error a failing physics function raises, and how its parameters are printed."""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["NonFiniteOutputError", "PhysicsModelError", "format_params"]


class PhysicsModelError(RuntimeError):
    """The physics function failed (raised, returned non-finite values or a wrong shape)."""


class NonFiniteOutputError(PhysicsModelError):
    """The physics function ran but returned NaN or inf (the model is undefined there)."""


def format_params(params: Mapping[str, float]) -> str:
    """Parameter values as ``{a=1, k=0.5}`` for error messages.

    Examples
    --------
    >>> format_params({"a": 1.0, "k": 0.123456789})
    '{a=1, k=0.123457}'
    """
    return "{" + ", ".join(f"{k}={float(v):.6g}" for k, v in params.items()) + "}"
