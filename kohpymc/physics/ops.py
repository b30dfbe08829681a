"""A numpy physics model as PyTensor Ops: ``G(X; θ)`` and its Jacobian ``∂G/∂θ``.

:class:`_PhysicsOp` evaluates the model in ``perform``; its ``grad`` is the
vector-Jacobian product ``g @ J`` with ``J`` from :class:`_PhysicsJacobianOp`, which
asks the model's backend (the user's Jacobian or finite differences).  Both take
``theta`` (p,) and ``X`` (n, d) and are differentiable only in θ.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pytensor.tensor as pt
from pytensor.gradient import disconnected_type
from pytensor.graph.basic import Apply
from pytensor.graph.op import Op

from kohpymc.physics.errors import PhysicsModelError, format_params

if TYPE_CHECKING:
    from kohpymc.physics.spec import PhysicsModel

__all__: list[str] = []


class _PhysicsOpBase(Op):
    """Shared plumbing: inputs ``theta`` (p,) and ``X`` (n, d), gradient only in θ."""

    __props__ = ("physics",)
    output_ndim = 1

    def __init__(self, physics: PhysicsModel) -> None:
        self.physics = physics

    def make_node(self, theta, X):
        theta = pt.as_tensor_variable(theta)
        X = pt.as_tensor_variable(X)
        out = pt.vector if self.output_ndim == 1 else pt.matrix
        return Apply(self, [theta, X], [out(dtype="float64")])

    def _unpack(self, theta, X) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        physics = self.physics
        arrays = {k: np.asarray(X[:, j]) for j, k in enumerate(physics.inputs)}
        params = dict(zip(physics.parameters, np.asarray(theta, float).tolist(), strict=True))
        return arrays, params

    def connection_pattern(self, node):
        return [[True], [False]]


class _PhysicsOp(_PhysicsOpBase):
    """``G(X; θ)`` as a PyTensor Op: output (n,); gradient ``g @ ∂G/∂θ``."""

    def __init__(self, physics: PhysicsModel) -> None:
        super().__init__(physics)
        self.jacobian_op = _PhysicsJacobianOp(physics)

    def perform(self, node, inputs, outputs):
        theta, X = inputs
        arrays, params = self._unpack(theta, X)
        physics = self.physics
        out = physics.evaluator.call(physics, arrays, X.shape[0], params)
        if not np.all(np.isfinite(out)):
            if physics.on_nonfinite == "raise":
                raise PhysicsModelError(
                    f"physics function {physics.name!r} returned non-finite values at "
                    f"parameters {format_params(params)} (pass on_nonfinite='reject', "
                    'in a study file [physics] on_nonfinite = "reject", to treat such points '
                    "as having zero likelihood)"
                )
            out = np.where(np.isfinite(out), out, np.inf)
        outputs[0][0] = out

    def grad(self, inputs, output_grads):
        theta, X = inputs
        (g,) = output_grads
        return [pt.dot(g, self.jacobian_op(theta, X)), disconnected_type()]

    def infer_shape(self, fgraph, node, shapes):
        return [(shapes[1][0],)]


class _PhysicsJacobianOp(_PhysicsOpBase):
    """``∂G/∂θ`` as an Op: output (n, p), from the user's Jacobian or finite differences."""

    output_ndim = 2

    def perform(self, node, inputs, outputs):
        theta, X = inputs
        arrays, params = self._unpack(theta, X)
        physics = self.physics
        outputs[0][0] = physics.evaluator.jacobian(physics, arrays, X.shape[0], params)

    def grad(self, inputs, output_grads):  # pragma: no cover - second derivatives unused
        raise NotImplementedError("second derivatives of a black-box physics model")

    def infer_shape(self, fgraph, node, shapes):
        return [(shapes[1][0], shapes[0][0])]
