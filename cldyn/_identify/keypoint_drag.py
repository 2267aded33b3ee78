"""Drag on a keypoint through the surrounding medium, linear or quadratic in its speed."""

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .._dissipation import KeypointDrag
from .base import (
    AbstractEffect,
    Candidate,
    add_dissipation,
    dissipation_terms,
    everywhere,
    keypoint_force,
    value,
)


class KeypointDragEffect(AbstractEffect):
    """Drag on a keypoint: `-c v` (kind `"linear"`) or `-c |v| v` (kind `"quadratic"`), `v` its
    velocity.

    Two candidates per keypoint, one of each kind. Reported as the coefficient `c` (N s/m or
    N s^2/m^2); added as `cldyn.KeypointDrag`, one term per detection, and read back as what the
    added terms hold together at that keypoint.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                effects=[cldyn.KeypointDragEffect()])
        ```
    """

    name: ClassVar[str] = "keypoint_drag"

    def candidates(self, context):
        return tuple(
            Candidate(self, name, i, kind=kind, acts_on="keypoint")
            for i, name in enumerate(context.keypoint_names)
            for kind in ("linear", "quadratic")
        )

    def force(self, candidate, context, point):
        v = point.xd[2 * candidate.index : 2 * candidate.index + 2]
        drag = -v if candidate.kind == "linear" else -jnp.sqrt(jnp.sum(v**2)) * v
        return keypoint_force(context, candidate, drag)[:, None]

    def parameters(self, candidate, theta):
        return value(theta)

    def augment(self, model, candidate, theta, context):
        coefficients = {"linear": np.zeros(model.size // 2), "quadratic": np.zeros(model.size // 2)}
        coefficients[candidate.kind][candidate.index] = theta[0]
        term = KeypointDrag(jnp.asarray(coefficients["linear"]), jnp.asarray(coefficients["quadratic"]))
        return add_dissipation(model, term)

    def refitted(self, model, candidate, context):
        def total(m):
            terms = [t for t in dissipation_terms(m) if isinstance(t, KeypointDrag)]
            return sum(float(getattr(t, candidate.kind)[candidate.index]) for t in terms)

        if not any(isinstance(t, KeypointDrag) for t in dissipation_terms(model)):
            return None
        return {"value": total(model) - total(context.model)}

    def unrepresentable(self, candidate, parameters, q):
        return everywhere(candidate, parameters, q)
