"""The constrained Euler-Lagrange equations in keypoint coordinates (KeyCLD eq. 6, appendix A.1)."""

import abc

import equinox as eqx
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from ._constraint import AbstractConstraint
from ._custom_types import ArrayInput, Scalar, Vector
from ._dissipation import AbstractDissipation
from ._input import AbstractInputMatrix
from ._linalg import small_matmul, small_solve
from ._mass import AbstractMass, JointArmature
from ._potential import AbstractPotential


def check_array(name: str, value, shape: tuple[int, ...]) -> Array:
    """`value` as a floating array of exactly `shape`, or a ValueError that names it."""
    if value is None:
        raise ValueError(f"{name} is missing; expected shape {shape}")
    array = jnp.asarray(value)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if not jnp.issubdtype(array.dtype, jnp.floating):
        array = array.astype(float)
    return array


class AbstractDynamics(eqx.Module):
    """Anything that gives keypoint accelerations `xdd(x, xd, u)`: what `simulate`, the losses and
    the evaluation tools need. `ConstrainedLagrangian` is the physical model; the baselines
    (for example `SecondOrderNeuralODE`) implement the same interface.
    """

    @property
    @abc.abstractmethod
    def size(self) -> int:
        """The number `k` of keypoint coordinates."""

    @property
    @abc.abstractmethod
    def num_inputs(self) -> int:
        """The number `l` of controls."""

    @property
    @abc.abstractmethod
    def num_constraints(self) -> int:
        """The number `n` of holonomic constraints (0 for unconstrained models)."""

    @abc.abstractmethod
    def acceleration(self, x: ArrayInput, xd: ArrayInput, u: ArrayInput | None = None) -> Vector:
        """The keypoint accelerations, shape `(k,)`, for positions and velocities `(k,)` and controls
        `(l,)` (no input force if `None`)."""


class ConstrainedLagrangian(AbstractDynamics):
    """A mechanical system in keypoint coordinates with holonomic constraints.

    The Lagrangian is $L(x, \\dot x) = \\tfrac12 \\dot x^T M \\dot x - V(x)$ with a constant mass matrix
    `M` (eq. 17), subject to constraints `Phi(x) = const`. The equations of motion are eq. 6:

    $\\ddot x = M^{-1} f - M^{-1} D\\Phi^T (D\\Phi M^{-1} D\\Phi^T)^{-1}
    (D\\Phi M^{-1} f + \\langle D^2\\Phi, \\dot x\\rangle \\dot x)$,
    $\\quad f = -\\nabla V(x) + g(x) u + F(x, \\dot x)$,

    where `F` collects the optional dissipative forces. Every component is an Equinox module, and
    every inexact array inside is a parameter that `cldyn.fit` can learn.

    **Arguments:**

    - `mass`: the constant mass matrix (`PointMasses`, `ConstantMass`).
    - `potential`: the potential energy `V(x)`, or `None` for none.
    - `constraint`: the holonomic constraints, or `None` for a free system.
    - `input_matrix`: `g(x)`, or `None` for an uncontrolled system.
    - `dissipation`: dissipative forces `F(x, xd)`, or `None`.
    - `armature`: rotor inertia on joints (`JointArmature`), or `None`.

    All methods act on a single state; batch them with `jax.vmap`.

    !!! example

        ```python
        pendulum = cldyn.ConstrainedLagrangian(
            mass=cldyn.PointMasses(jnp.array([1.0])),
            potential=cldyn.Gravity.from_masses(jnp.array([1.0])),
            constraint=cldyn.Anchor(0),
        )
        xdd = pendulum.acceleration(jnp.array([1.0, 0.0]), jnp.zeros(2))
        ```
    """

    mass: AbstractMass
    potential: AbstractPotential | None = None
    constraint: AbstractConstraint | None = None
    input_matrix: AbstractInputMatrix | None = None
    dissipation: AbstractDissipation | None = None
    armature: JointArmature | None = None

    def __check_init__(self):
        checks = (
            ("mass", self.mass, AbstractMass, False),
            ("potential", self.potential, AbstractPotential, True),
            ("constraint", self.constraint, AbstractConstraint, True),
            ("input_matrix", self.input_matrix, AbstractInputMatrix, True),
            ("dissipation", self.dissipation, AbstractDissipation, True),
            ("armature", self.armature, JointArmature, True),
        )
        for name, value, kind, optional in checks:
            if value is None and optional:
                continue
            if not isinstance(value, kind):
                raise TypeError(f"{name} must be a {kind.__name__}, got {type(value).__name__}")

    @property
    def size(self) -> int:
        """The number `k` of keypoint coordinates."""
        return self.mass.size

    @property
    def num_constraints(self) -> int:
        """The number `n` of scalar constraints."""
        return 0 if self.constraint is None else self.constraint.num_constraints

    @property
    def num_inputs(self) -> int:
        """The number `l` of controls."""
        return 0 if self.input_matrix is None else self.input_matrix.num_inputs

    @property
    def degrees_of_freedom(self) -> int:
        """`m = k - n`, assuming independent constraints."""
        return self.size - self.num_constraints

    # -- argument checking (at trace time: shapes are static) --------------------------------

    def _state(self, x, xd=None, u=None, *, need_velocity=True, need_control=True):
        k, num_inputs = self.size, self.num_inputs
        x = check_array("x", x, (k,))
        if need_velocity:
            xd = check_array("xd", xd, (k,))
        if need_control and u is not None:
            u = check_array("u", u, (num_inputs,))
        return x, xd, u

    # -- energies --------------------------------------------------------------------------

    def kinetic_energy(self, x: ArrayInput, xd: ArrayInput) -> Scalar:
        """The kinetic energy $T = \\tfrac12 \\dot x^T M \\dot x$ (plus joint armature)."""
        x, xd, _ = self._state(x, xd, need_control=False)
        energy = self.mass.kinetic_energy(xd)
        if self.armature is not None:
            energy = energy + self.armature.kinetic_energy(x, xd)
        return energy

    def potential_energy(self, x: ArrayInput) -> Scalar:
        """The potential energy `V(x)`."""
        x, _, _ = self._state(x, need_velocity=False, need_control=False)
        if self.potential is None:
            return jnp.zeros((), dtype=x.dtype)
        return self.potential(x)

    def energy(self, x: ArrayInput, xd: ArrayInput) -> Scalar:
        """The total energy `E = T + V`."""
        return self.kinetic_energy(x, xd) + self.potential_energy(x)

    def power(self, x: ArrayInput, xd: ArrayInput, u: ArrayInput | None = None) -> Scalar:
        """`dE/dt` along the motion: $\\dot x \\cdot (g(x) u + F(x, \\dot x))$.

        Constraint forces do no work on velocities that satisfy the constraints, so this is the power
        of the inputs and of the dissipative forces only.
        """
        x, xd, u = self._state(x, xd, u)
        return jnp.dot(xd, self._external_force(x, xd, u))

    # -- forces ----------------------------------------------------------------------------

    def _external_force(self, x, xd, u) -> Vector:
        force = jnp.zeros_like(x)
        if u is not None and self.input_matrix is not None and self.num_inputs > 0:
            force = force + self.input_matrix(x) @ u
        if self.dissipation is not None:
            force = force + self.dissipation(x, xd)
        return force

    def generalized_force(self, x: ArrayInput, xd: ArrayInput, u: ArrayInput | None = None) -> Vector:
        """All forces but the constraint forces: $f = -\\nabla V + g u + F$ (eq. 6, 19).

        With armature this includes its velocity-product force.
        """
        x, xd, u = self._state(x, xd, u)
        return self._force(x, xd, u)

    def _force(self, x, xd, u) -> Vector:
        force = self._external_force(x, xd, u)
        if self.potential is not None:
            force = force - self.potential.gradient(x)
        if self.armature is not None:
            force = force + self.armature.bias(x, xd)
        return force

    def inverse_dynamics(
        self, x: ArrayInput, xd: ArrayInput, xdd: ArrayInput, u: ArrayInput | None = None
    ) -> Vector:
        """The force `M(x) xdd - f(x, xd, u)` that the motion `xdd` needs beyond the modelled forces.

        For a motion that the model explains, this is the constraint force `DPhi^T lambda`, which has no
        component along the constraint manifold; what it has along the manifold is what the model
        misses (see `cldyn.identify`).

        **Arguments:**

        - `x`, `xd`, `xdd`: positions, velocities and accelerations, shape `(k,)`.
        - `u`: controls, shape `(l,)`; no input force if omitted.

        **Returns:** shape `(k,)`.
        """
        x, xd, u = self._state(x, xd, u)
        xdd = check_array("xdd", xdd, (self.size,))
        inertial = self.mass.matvec(xdd)
        if self.armature is not None:
            grads = self.armature.gradients(x)
            inertial = inertial + grads @ (self.armature.armature * (grads.T @ xdd))
        return inertial - self._force(x, xd, u)

    def _mass_solve(self, x: Vector, rhs: Float[Array, "k m"]) -> Float[Array, "k m"]:
        """`M(x)^-1 rhs`; with armature, by the Woodbury identity around the constant `M`."""
        base = self.mass.solve(rhs)
        if self.armature is None:
            return base
        grads = self.armature.gradients(x)
        root = jnp.sqrt(jnp.maximum(self.armature.armature, 0.0))
        scaled = grads * root[None, :]
        minv_scaled = self.mass.solve(scaled)
        capacitance = jnp.eye(scaled.shape[1], dtype=scaled.dtype) + scaled.T @ minv_scaled
        return base - minv_scaled @ small_solve(capacitance, scaled.T @ base)

    def _terms(self, x, xd, u):
        """`(M^-1 f, M^-1 DPhi^T, DPhi, curvature)`."""
        f = self._force(x, xd, u)
        jac = self.constraint.jacobian(x)
        curvature = self.constraint.curvature(x, xd)
        solved = self._mass_solve(x, jnp.concatenate([f[:, None], jac.T], axis=1))
        return solved[:, 0], solved[:, 1:], jac, curvature

    def acceleration(self, x: ArrayInput, xd: ArrayInput, u: ArrayInput | None = None) -> Vector:
        """The acceleration `xdd` of eq. 6.

        Redundant constraints (a rank-deficient `DPhi`) still give the unique, finite acceleration.

        **Arguments:**

        - `x`: keypoint positions, shape `(k,)`.
        - `xd`: keypoint velocities, shape `(k,)`.
        - `u`: controls, shape `(l,)`; no input force if omitted.

        **Returns:** the keypoint accelerations, shape `(k,)`.
        """
        x, xd, u = self._state(x, xd, u)
        return self._acceleration(x, xd, u, None)

    def _acceleration(self, x, xd, u, target: Array | None) -> Vector:
        """Eq. 6, with the constraint acceleration `DPhi xdd` driven to `-curvature + target`.

        `target = None` (zero) is the exact constrained motion; stabilisation schemes such as
        Baumgarte's pass a feedback on the constraint drift.
        """
        if self.num_constraints == 0:
            f = self._force(x, xd, u)
            return self._mass_solve(x, f[:, None])[:, 0]
        minv_f, minv_jt, jac, curvature = self._terms(x, xd, u)
        rhs = small_matmul(jac, minv_f) + curvature
        if target is not None:
            rhs = rhs - target
        lam = -small_solve(small_matmul(jac, minv_jt), rhs)
        return minv_f + small_matmul(minv_jt, lam)

    def multipliers(self, x: ArrayInput, xd: ArrayInput, u: ArrayInput | None = None) -> Float[Array, " n"]:
        """The Lagrange multipliers `lambda` with $M \\ddot x = f + D\\Phi^T \\lambda$ (eq. 19, 22).

        For redundant constraints the multipliers are not unique; this returns the least-squares
        solution of least norm (by SVD), which shares the load equally between duplicates.

        **Returns:** shape `(n,)`; for `Distance` and `Anchor` constraints, the tension in newtons
        (negative when the segment is pulled apart).
        """
        x, xd, u = self._state(x, xd, u)
        if self.num_constraints == 0:
            return jnp.zeros(0, dtype=x.dtype)
        minv_f, minv_jt, jac, curvature = self._terms(x, xd, u)
        operator = lx.MatrixLinearOperator(jac @ minv_jt)
        return -lx.linear_solve(operator, jac @ minv_f + curvature, lx.SVD()).value

    def constraint_force(self, x: ArrayInput, xd: ArrayInput, u: ArrayInput | None = None) -> Vector:
        """The constraint force $D\\Phi(x)^T \\lambda$ on the keypoints, shape `(k,)`."""
        x, xd, u = self._state(x, xd, u)
        if self.num_constraints == 0:
            return jnp.zeros_like(x)
        return self.constraint.jacobian(x).T @ self.multipliers(x, xd, u)

    def constraint_violation(self, x: ArrayInput, xd: ArrayInput, reference: ArrayInput) -> tuple:
        """`(Phi(x) - reference, DPhi(x) xd)`: how far a state is from the constraint manifold."""
        x, xd, _ = self._state(x, xd, need_control=False)
        if self.num_constraints == 0:
            empty = jnp.zeros(0, dtype=x.dtype)
            return empty, empty
        return self.constraint(x) - reference, self.constraint.velocity(x, xd)

