"""Quadratic (aerodynamic) joint damping."""

from typing import ClassVar

import jax.numpy as jnp

from .._dissipation import JointQuadraticDamping
from .base import (
    AbstractEffect,
    add_dissipation,
    dissipation_terms,
    everywhere,
    joint_candidates,
    joint_rate,
    joint_term_value,
    value,
)


class JointQuadraticDampingEffect(AbstractEffect):
    """Quadratic damping on a joint, drag that grows with the square of the joint speed: joint force
    `-c |qd| qd`, Cartesian force `-c grad q |qd| qd` with `qd = grad q . xd`.

    Reported as the coefficient `c` (N m s^2/rad^2 or N s^2/m^2; MuJoCo has no such attribute);
    added as `cldyn.JointQuadraticDamping`.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                effects=[cldyn.JointDampingEffect(), cldyn.JointQuadraticDampingEffect()])
        ```
    """

    name: ClassVar[str] = "joint_quadratic_damping"

    def candidates(self, context):
        return joint_candidates(self, context)

    def force(self, candidate, context, point):
        grad, rate = joint_rate(context, candidate, point)
        return (-grad * jnp.abs(rate) * rate)[:, None]

    def parameters(self, candidate, theta):
        return value(theta)

    def augment(self, model, candidate, theta, context):
        term = JointQuadraticDamping([context.coordinates[candidate.index]], theta[0])
        return add_dissipation(model, term)

    def refitted(self, model, candidate, context):
        found = joint_term_value(
            dissipation_terms(model), JointQuadraticDamping, "damping", context.coordinates[candidate.index]
        )
        return None if found is None else {"value": found}

    def unrepresentable(self, candidate, parameters, q):
        return everywhere(candidate, parameters, q)
