"""A spring on a joint: MuJoCo's `stiffness` with `springref`."""

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .._potential import JointSpring
from .base import AbstractEffect, add_potential, joint_candidates, potential_terms, same


class JointSpringEffect(AbstractEffect):
    """A spring on a joint: joint force `-k (q - q0) = -k q + k q0`, linear in `(k, k q0)`.

    The joint angle is unwrapped along each run, so a spring's force stays continuous where the angle
    passes `pi`. Reported as MuJoCo's `stiffness` `k` (the value) and `springref` `q0` (radians or
    metres); added as `cldyn.JointSpring`.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                effects=[cldyn.JointSpringEffect()])
        ```
    """

    name: ClassVar[str] = "joint_spring"
    columns: ClassVar[tuple[str, ...]] = ("stiffness", "stiffness*springref")
    signs: ClassVar[tuple[int, ...]] = (1, 0)

    def candidates(self, context):
        return joint_candidates(self, context)

    def force(self, candidate, context, point):
        grad = context.coordinates[candidate.index].gradient(point.x)
        return jnp.stack([-grad * point.q[candidate.index], grad], axis=1)

    def parameters(self, candidate, theta):
        stiffness = float(theta[0])
        rest = float(theta[1] / theta[0]) if stiffness != 0 else float("nan")
        return {"value": stiffness, "stiffness": stiffness, "springref": rest}

    def augment(self, model, candidate, theta, context):
        coordinate = context.coordinates[candidate.index]
        term = JointSpring(coordinate, stiffness=theta[0], rest=theta[1] / theta[0], periodic=True)
        return add_potential(model, term)

    def refitted(self, model, candidate, context):
        found = None
        for term in potential_terms(model):
            if isinstance(term, JointSpring) and same(term.coordinate, context.coordinates[candidate.index]):
                stiffness = float(term.stiffness)
                found = {"value": stiffness, "stiffness": stiffness, "springref": float(term.rest)}
        return found

    def unrepresentable(self, candidate, parameters, q):
        # the keypoints give the angle modulo a turn: beyond half a turn from the rest, the spring's
        # force in the data (MuJoCo counts turns) and in the keypoint model differ
        return np.abs(q[..., candidate.index] - parameters["springref"]) > np.pi
