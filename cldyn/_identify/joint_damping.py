"""Viscous joint damping: MuJoCo's joint `damping`."""

from typing import ClassVar

from .._dissipation import JointDamping
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


class JointDampingEffect(AbstractEffect):
    """Viscous damping on a joint: joint force `-b qd`, Cartesian force `-b grad q (grad q . xd)`.

    Reported as MuJoCo's joint `damping` `b` (N m s/rad or N s/m); added as `cldyn.JointDamping`.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                effects=[cldyn.JointDampingEffect()])
        ```
    """

    name: ClassVar[str] = "joint_damping"

    def candidates(self, context):
        return joint_candidates(self, context)

    def force(self, candidate, context, point):
        grad, rate = joint_rate(context, candidate, point)
        return (-grad * rate)[:, None]

    def parameters(self, candidate, theta):
        return value(theta)

    def augment(self, model, candidate, theta, context):
        return add_dissipation(model, JointDamping([context.coordinates[candidate.index]], theta[0]))

    def refitted(self, model, candidate, context):
        found = joint_term_value(
            dissipation_terms(model), JointDamping, "damping", context.coordinates[candidate.index]
        )
        return None if found is None else {"value": found}

    def unrepresentable(self, candidate, parameters, q):
        return everywhere(candidate, parameters, q)
