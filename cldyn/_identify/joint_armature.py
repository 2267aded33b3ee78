"""Rotor inertia reflected onto a joint: MuJoCo's `armature`."""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._mass import JointArmature
from .base import AbstractEffect, everywhere, joint_acceleration, joint_candidates, same, value


class JointArmatureEffect(AbstractEffect):
    """Armature on a joint: joint force `-a qdd`, with `qdd = grad q . xdd + xd^T D2q xd`.

    Reported as MuJoCo's `armature` `a` (kg m^2 or kg); added as `cldyn.JointArmature` (the model's
    own, extended by one joint).

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                effects=[cldyn.JointArmatureEffect()])
        ```
    """

    name: ClassVar[str] = "joint_armature"

    def candidates(self, context):
        return joint_candidates(self, context)

    def force(self, candidate, context, point):
        coordinate = context.coordinates[candidate.index]
        return (-coordinate.gradient(point.x) * joint_acceleration(coordinate, point))[:, None]

    def parameters(self, candidate, theta):
        return value(theta)

    def augment(self, model, candidate, theta, context):
        coordinate = context.coordinates[candidate.index]
        if model.armature is None:
            armature = JointArmature([coordinate], theta[0])
        else:
            armature = JointArmature(
                model.armature.coordinates + (coordinate,),
                jnp.concatenate([model.armature.armature, jnp.asarray(theta[:1])]),
            )
        return eqx.tree_at(lambda s: s.armature, model, armature, is_leaf=lambda v: v is None)

    def refitted(self, model, candidate, context):
        if model.armature is None:
            return None
        found = None
        for coordinate, armature in zip(model.armature.coordinates, model.armature.armature):
            if same(coordinate, context.coordinates[candidate.index]):
                found = {"value": float(armature)}
        return found

    def unrepresentable(self, candidate, parameters, q):
        return everywhere(candidate, parameters, q)
