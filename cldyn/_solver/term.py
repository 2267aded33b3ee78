"""`DynamicsTerm`: eq. 6 as a diffrax term, with the mechanical pieces that constrained solvers use."""

from typing import Any

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, Float

from .._control import AbstractControl
from .._custom_types import Control, Vector
from .._linalg import small_matmul, small_solve
from .._stabilisation import AbstractStabilisation, NoStabilisation
from .._system import AbstractDynamics, ConstrainedLagrangian

State = tuple[Vector, Vector]


class DynamicsTerm(dfx.AbstractTerm):
    """The equations of motion of a system in keypoint coordinates as a diffrax term.

    The state is the pair `y = (x, xd)`; the vector field is $(\\dot x, \\ddot x(x, \\dot x, u(t, x,
    \\dot x)))$ with the acceleration of eq. 6 (or of any other `AbstractDynamics`). Besides the vector
    field, the term gives constrained solvers such as `RATTLE` the mechanical pieces they step with:
    the forces, the mass matrix, the constraint residual `Phi(x) - reference` and its Jacobian, and
    the projection of velocities onto the constraint tangent space. `cldyn.simulate` builds one; build
    it yourself to call `diffrax.diffeqsolve` directly.

    **Arguments:**

    - `system`: the `ConstrainedLagrangian` (or another `AbstractDynamics`; `RATTLE` needs a
      `ConstrainedLagrangian`).
    - `reference`: the constraint values to hold, `Phi(x0)` for a start `x0`, shape `(n,)`; may be
      omitted for a system without constraints.
    - `control`: an `AbstractControl`, or `None` for no input.
    - `stabilisation`: supplies a drift feedback to the vector field (`Baumgarte`); the default
      `NoStabilisation()` leaves eq. 6 as it is. (A `Projection` acts through the solver: see
      `Projection.wrap`.)

    !!! example

        ```python
        system, joints = cldyn.systems.pendulum()
        x0, xd0 = joints.to_keypoints(jnp.array([2.0]), jnp.zeros(1))
        term = cldyn.DynamicsTerm(system, system.constraint(x0))
        solution = diffrax.diffeqsolve(term, cldyn.RATTLE(), 0.0, 10.0, 0.01, (x0, xd0))
        ```
    """

    system: AbstractDynamics
    reference: Float[Array, " n"] | None = None
    control: AbstractControl | None = None
    stabilisation: AbstractStabilisation = NoStabilisation()

    def __check_init__(self):
        if not isinstance(self.system, AbstractDynamics):
            raise TypeError(f"system must be an AbstractDynamics, got {type(self.system).__name__}")
        if self.control is not None and not isinstance(self.control, AbstractControl):
            raise TypeError(f"control must be an AbstractControl, got {type(self.control).__name__}")
        if not isinstance(self.stabilisation, AbstractStabilisation):
            raise TypeError("stabilisation must be an AbstractStabilisation")
        n = self.system.num_constraints
        if self.reference is None:
            if n > 0:
                raise ValueError(
                    "DynamicsTerm needs the constraint values to hold: pass reference=system.constraint(x0)"
                )
        elif jnp.shape(self.reference) != (n,):
            raise ValueError(f"reference must have shape ({n},), got {jnp.shape(self.reference)}")

    # -- the diffrax term --------------------------------------------------------------------

    def vf(self, t, y: State, args) -> State:
        """`(xd, xdd)` at time `t` in state `y = (x, xd)`."""
        del args
        x, xd = y
        u = self.inputs(t, x, xd)
        feedback = self.stabilisation.feedback(self, x, xd)
        if feedback is None:
            return xd, self.system.acceleration(x, xd, u)
        return xd, self.system._acceleration(x, xd, u, feedback)

    def contr(self, t0, t1, **kwargs):
        del kwargs
        return t1 - t0

    def prod(self, vf: State, control) -> State:
        return jtu.tree_map(lambda v: control * v, vf)

    # -- mechanics for constrained solvers ------------------------------------------------------

    def inputs(self, t, x: Vector, xd: Vector) -> Control | None:
        """The controls `u(t, x, xd)`, shape `(l,)`, or `None` without a control."""
        return None if self.control is None else self.control(t, x, xd)

    def force(self, t, x: Vector, xd: Vector) -> Vector:
        """All forces but the constraint forces, $f = -\\nabla V + g u + F$ (eq. 6), at time `t`."""
        return self.system.generalized_force(x, xd, self.inputs(t, x, xd))

    @property
    def depends_on_velocity(self) -> bool:
        """Whether the forces depend on the velocity (dissipation, or a feedback control)."""
        dissipative = isinstance(self.system, ConstrainedLagrangian) and self.system.dissipation is not None
        return dissipative or (self.control is not None and self.control.depends_on_state)

    def mass_solve(self, rhs: Float[Array, "k ..."]) -> Float[Array, "k ..."]:
        """`M^-1 rhs` with the constant mass matrix `M` (eq. 17); joint armature is not included."""
        return self.system.mass.solve(rhs)

    def residual(self, x: Vector) -> Float[Array, " n"]:
        """The constraint drift `Phi(x) - reference`, shape `(n,)`."""
        return self.system.constraint(x) - self.reference

    def jacobian(self, x: Vector) -> Float[Array, "n k"]:
        """The constraint Jacobian `DPhi(x)`, shape `(n, k)`."""
        return self.system.constraint.jacobian(x)

    def rate(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        """The constraint velocity `DPhi(x) xd`, shape `(n,)`."""
        return self.system.constraint.velocity(x, xd)

    def tangent(self, x: Vector, xd: Vector) -> Vector:
        """The mass-weighted projection of `xd` onto the tangent space `DPhi(x) xd = 0`:
        $\\dot x - M^{-1} D\\Phi^T (D\\Phi M^{-1} D\\Phi^T)^{-1} D\\Phi \\dot x$."""
        if self.system.num_constraints == 0:
            return xd
        jac = self.jacobian(x)
        minv_jt = self.mass_solve(jac.T)
        mu = small_solve(small_matmul(jac, minv_jt), small_matmul(jac, xd))
        return xd - small_matmul(minv_jt, mu)


def unwrap_term(terms) -> tuple[DynamicsTerm, Any]:
    """The `DynamicsTerm` inside the terms that `diffrax.diffeqsolve` hands its solver, and the
    direction of time.

    diffeqsolve wraps every term (its private `WrapTerm`, holding `term` and `direction`) so that it
    can integrate backwards in time by flipping the sign of `t`; solvers see times multiplied by
    `direction`. Constrained solvers need the mechanical methods of the `DynamicsTerm` itself.
    """
    direction = 1
    while not isinstance(terms, DynamicsTerm):
        if not hasattr(terms, "term"):
            raise TypeError(f"expected a cldyn.DynamicsTerm, got {type(terms).__name__}")
        direction = direction * getattr(terms, "direction", 1)
        terms = terms.term
    return terms, direction


def replace_term(terms, term: DynamicsTerm):
    """`terms` (a `DynamicsTerm`, possibly inside diffrax's wrappers) with its `DynamicsTerm`
    replaced by `term`."""
    if isinstance(terms, DynamicsTerm):
        return term
    return eqx.tree_at(lambda s: s.term, terms, replace_term(terms.term, term))
