"""An actuator that delivers more or less force than the model says: a gear (gain) error."""

from typing import ClassVar

import equinox as eqx

from .._input import JointInput
from .base import AbstractEffect, Candidate, everywhere


class ActuatorGainEffect(AbstractEffect):
    """A gain error on an actuator: force `(rho - 1) g_a(x) u_a`, with `g_a` the model's input column.

    Needs a `JointInput` (gears); no candidates otherwise. Reported as the ratio `rho` of the true to
    the nominal gear; applied by scaling the gear. The gears are not refitted (the equations of
    motion are homogeneous in the mass, the potential, the gears and the forces: one must fix the
    scale), so the estimate stands.

    !!! example

        ```python
        result = cldyn.identify(model, data, joint_coordinates=coordinates,
                                effects=[cldyn.ActuatorGainEffect()])
        ```
    """

    name: ClassVar[str] = "actuator_gain"
    columns: ClassVar[tuple[str, ...]] = ("ratio-1",)
    signs: ClassVar[tuple[int, ...]] = (0,)

    def candidates(self, context):
        if not isinstance(context.model.input_matrix, JointInput):
            return ()
        return tuple(
            Candidate(self, name, a, acts_on="actuator") for a, name in enumerate(context.actuator_names)
        )

    def force(self, candidate, context, point):
        a = candidate.index
        return (context.model.input_matrix(point.x)[:, a] * point.u[a])[:, None]

    def parameters(self, candidate, theta):
        return {"value": 1.0 + float(theta[0])}

    def augment(self, model, candidate, theta, context):
        gears = model.input_matrix.gears
        return eqx.tree_at(
            lambda s: s.input_matrix.gears, model, gears.at[candidate.index].multiply(1.0 + theta[0])
        )

    def refitted(self, model, candidate, context):
        return None

    def unrepresentable(self, candidate, parameters, q):
        return everywhere(candidate, parameters, q)
