"""Physics models y = G(x; θ) and their wrapping as PyTensor Ops with gradients.

A user hands over a plain numpy function ``model(inputs, params) -> ndarray`` where
``inputs`` maps input names to 1-D arrays (one entry per data row) and ``params`` maps
parameter names to floats.  :class:`PhysicsModel` wraps it as a PyTensor ``Op`` whose
gradient is the vector-Jacobian product ``g @ J``; ``J = ∂G/∂θ`` comes from a
user-supplied Jacobian when given, otherwise from finite differences (central by
default, see :mod:`kohpymc.physics.finite_differences`).  NUTS needs one gradient per
leapfrog step, so a finite-difference gradient costs ``2p`` (or ``p + 1``) times one
model run: supply ``jacobian=`` when you can.

A model written with ``pytensor.tensor`` operations (``backend="pytensor"``) is put
into the graph directly and gets exact automatic differentiation.

Layers:

* :mod:`~kohpymc.physics.spec`: :class:`PhysicsModel`, the specification (inputs,
  parameters and priors, options) and the handling of user values;
* :mod:`~kohpymc.physics.backends`: one strategy per kind of function (numpy, pytensor)
  that evaluates it, gives its Jacobian and builds its tensor;
* :mod:`~kohpymc.physics.finite_differences`: finite-difference Jacobians;
* :mod:`~kohpymc.physics.ops`: the black-box PyTensor Ops of a numpy model;
* :mod:`~kohpymc.physics.errors`: :class:`PhysicsModelError`.
"""

from kohpymc.physics.errors import PhysicsModelError
from kohpymc.physics.spec import PhysicsModel

__all__ = ["PhysicsModel", "PhysicsModelError"]
