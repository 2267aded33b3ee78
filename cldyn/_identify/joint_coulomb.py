"""Coulomb friction on a joint: MuJoCo's `frictionloss`, smoothed."""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._dissipation import JointCoulomb
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


class JointCoulombEffect(AbstractEffect):
    """Coulomb friction on a joint: joint force `-f tanh(qd / v_s)`.

    MuJoCo's `frictionloss` sticks exactly; the smooth `tanh` keeps the features differentiable, so
    values are accurate to about 10%. Reported as `frictionloss` `f` (N m or N); added as
    `cldyn.JointCoulomb`.

    **Arguments:**

    - `velocity_scale`: `v_s`, the joint speed below which the friction force is proportional to
      speed (rad/s or m/s).

    !!! example

        ```python
        effects = [cldyn.JointCoulombEffect(velocity_scale=0.02), cldyn.JointDampingEffect()]
        ```
    """

    velocity_scale: float = eqx.field(static=True, default=0.05)
    name: ClassVar[str] = "joint_coulomb"

    def __check_init__(self):
        if not self.velocity_scale > 0:
            raise ValueError(f"velocity_scale must be positive, got {self.velocity_scale}")

    def candidates(self, context):
        return joint_candidates(self, context)

    def force(self, candidate, context, point):
        grad, rate = joint_rate(context, candidate, point)
        return (-grad * jnp.tanh(rate / self.velocity_scale))[:, None]

    def parameters(self, candidate, theta):
        return value(theta)

    def augment(self, model, candidate, theta, context):
        coordinate = context.coordinates[candidate.index]
        return add_dissipation(
            model, JointCoulomb([coordinate], theta[0], velocity_scale=self.velocity_scale)
        )

    def refitted(self, model, candidate, context):
        found = joint_term_value(
            dissipation_terms(model), JointCoulomb, "friction", context.coordinates[candidate.index]
        )
        return None if found is None else {"value": found}

    def unrepresentable(self, candidate, parameters, q):
        return everywhere(candidate, parameters, q)
