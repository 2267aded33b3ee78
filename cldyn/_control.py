"""Energy-shaping control in keypoint coordinates (KeyCLD eq. 15, appendix A.5)."""

import equinox as eqx
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from ._custom_types import ArrayInput, Control, Vector
from ._linalg import SmallDense
from ._system import ConstrainedLagrangian, check_array


class EnergyShaping(eqx.Module):
    """Passivity-based energy-shaping controller (eq. 32).

    $u = (g^T g)^{-1} g^T [\\nabla_x V(x) - k_p (x - x^*)] - k_d\\, g^T \\dot x$

    The first term replaces the system's potential `V` by the shaped potential
    $V_d = \\tfrac12 k_p |x - x^*|^2$ with its minimum at the target; the second injects damping through
    the passive output $g^T \\dot x$. For a fully actuated system (`l` equal to the degrees of freedom)
    the matching condition of eq. 30 holds and the target is asymptotically stable. `(g^T g)^-1` is
    applied by a linear solve. Works with analytic and learned systems alike: only `V(x)` and `g(x)`
    are used.

    **Arguments:**

    - `system`: a `ConstrainedLagrangian` with a potential and an input matrix.
    - `x_target`: the target keypoints `x*`, shape `(k,)`.
    - `kp`: the stiffness of the shaped potential (the paper uses 5).
    - `kd`: the damping injection gain (the paper uses 2).
    - `limit`: optional bound on `|u|` per input (actuator saturation).
    - `project`: match in the constraint tangent space (see above); `False` for the literal eq. 32.
    - `damping`: `"keypoint"` (default) matches the keypoint damping force `-k_d xd` through the same
      `(g^T g)^-1 g^T` as the shaped force, so that `k_d` is a damping coefficient in N s/m whatever the
      scale of `g`; `"output"` injects `-k_d g^T xd` on the passive output as eq. 32 prints it. Both are
      passive. With the output form the damping grows with the square of the actuators' gears (and of
      a learned `g`'s arbitrary scale): with MuJoCo's KeyCLD scenes (gear 2) the paper's `k_d = 2` makes
      the swing-up so overdamped that it takes far longer than 10 s.

    Call it as a feedback policy `u = controller(t, x, xd)`, e.g. `cldyn.simulate(...,
    control=controller)`.

    !!! example

        ```python
        system, joints = cldyn.systems.pendulum()
        upright = joints.keypoints(jnp.array([jnp.pi]))
        controller = cldyn.EnergyShaping(system, upright, kp=5.0, kd=2.0)
        traj = cldyn.simulate(system, x0, xd0, ts, control=controller)
        ```
    """

    system: ConstrainedLagrangian
    x_target: Float[Array, " k"]
    kp: Float[Array, ""]
    kd: Float[Array, ""]
    limit: float | None = eqx.field(static=True)
    project: bool = eqx.field(static=True)
    damping: str = eqx.field(static=True)

    def __init__(
        self,
        system: ConstrainedLagrangian,
        x_target: ArrayInput,
        kp: float = 5.0,
        kd: float = 2.0,
        *,
        limit: float | None = None,
        project: bool = True,
        damping: str = "keypoint",
    ):
        if not isinstance(system, ConstrainedLagrangian):
            raise TypeError(f"system must be a ConstrainedLagrangian, got {type(system).__name__}")
        if system.input_matrix is None or system.num_inputs == 0:
            raise ValueError("energy shaping needs a system with inputs (an input_matrix)")
        self.system = system
        self.x_target = check_array("x_target", x_target, (system.size,))
        self.kp = jnp.asarray(kp, dtype=float)
        self.kd = jnp.asarray(kd, dtype=float)
        if limit is not None and not limit > 0:
            raise ValueError(f"limit must be positive, got {limit}")
        self.limit = limit
        self.project = project
        if damping not in ("output", "keypoint"):
            raise ValueError(f"damping must be 'output' or 'keypoint', got {damping!r}")
        self.damping = damping

    def shaped_potential(self, x: Vector) -> Float[Array, ""]:
        """The desired potential $V_d(x) = \\tfrac12 k_p |x - x^*|^2$ (eq. 31)."""
        return 0.5 * self.kp * jnp.sum((x - self.x_target) ** 2)

    def __call__(self, t, x: Vector, xd: Vector) -> Control:
        """The control `u(t, x, xd)`, shape `(l,)`."""
        del t
        g = self.system.input_matrix(x)
        if self.project and self.system.num_constraints > 0:
            jac = self.system.constraint.jacobian(x)
            normal = lx.MatrixLinearOperator(jac @ jac.T, lx.positive_semidefinite_tag)
            g = g - jac.T @ jnp.stack(
                [lx.linear_solve(normal, jac @ g[:, j], SmallDense()).value for j in range(g.shape[1])],
                axis=1,
            )
        grad_v = (
            self.system.potential.gradient(x) if self.system.potential is not None else jnp.zeros_like(x)
        )
        force = grad_v - self.kp * (x - self.x_target)
        if self.damping == "keypoint":
            force = force - self.kd * xd
        gram = lx.MatrixLinearOperator(g.T @ g, lx.positive_semidefinite_tag)
        u = lx.linear_solve(gram, g.T @ force, SmallDense()).value
        if self.damping == "output":
            u = u - self.kd * (g.T @ xd)
        if self.limit is not None:
            u = jnp.clip(u, -self.limit, self.limit)
        return u
