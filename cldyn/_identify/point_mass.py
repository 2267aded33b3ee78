"""A mass the model does not know of, carried by a keypoint (a payload)."""

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .._mass import ConstantMass, PointMasses
from .._potential import Gravity
from .base import AbstractEffect, Candidate, add_potential, everywhere, gravity_of, keypoint_force, value


class PointMassEffect(AbstractEffect):
    """A point mass `m` at a keypoint: force `-m (xdd_i + g e_y)` (its inertia and its weight).

    Reported as the mass `m` (kg); added to the mass matrix, with its weight as a `cldyn.Gravity`
    term. The mass matrix is not refitted, so the estimate stands.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                effects=[cldyn.PointMassEffect()])
        ```
    """

    name: ClassVar[str] = "point_mass"

    def candidates(self, context):
        return tuple(
            Candidate(self, name, i, acts_on="keypoint") for i, name in enumerate(context.keypoint_names)
        )

    def force(self, candidate, context, point):
        i = candidate.index
        weight = jnp.array([0.0, context.gravity], dtype=point.x.dtype)
        return keypoint_force(context, candidate, -(point.xdd[2 * i : 2 * i + 2] + weight))[:, None]

    def parameters(self, candidate, theta):
        return value(theta)

    def augment(self, model, candidate, theta, context):
        i, mass = candidate.index, float(theta[0])
        if isinstance(model.mass, PointMasses):
            new_mass = PointMasses(model.mass.masses.at[i].add(mass), dim=model.mass.dim)
        else:
            block = slice(2 * i, 2 * i + 2)
            new_mass = ConstantMass(model.mass.matrix().at[block, block].add(mass * jnp.eye(2)))
        weights = jnp.zeros(model.size).at[2 * i + 1].set(mass)
        model = eqx.tree_at(lambda s: s.mass, model, new_mass)
        return add_potential(model, Gravity(weights, gravity_of(model)))

    def refitted(self, model, candidate, context):
        return None

    def unrepresentable(self, candidate, parameters, q):
        return everywhere(candidate, parameters, q)
