"""Non-conservative forces `F(x, xd)` that remove energy: damping, friction, drag.

Each returns a generalised force on the keypoints, shape `(k,)`, added to `f` in eq. 6. Joint effects
act through a joint coordinate `q(x)` (see `HingeAngle`, `SliderPosition`): a joint force `tau` is the
keypoint force `tau grad q(x)`.
"""

import abc
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._coordinates import AbstractCoordinate
from ._custom_types import ArrayInput, Scalar, Vector


class AbstractDissipation(eqx.Module):
    """A velocity-dependent force `F(x, xd)` with `xd . F <= 0`; dissipations add up with `+`."""

    @abc.abstractmethod
    def __call__(self, x: Vector, xd: Vector) -> Vector:
        """Evaluate the force.

        **Arguments:**

        - `x`, `xd`: keypoint positions and velocities, shape `(k,)`.

        **Returns:** the generalised force on the keypoints, shape `(k,)`.
        """

    def power(self, x: Vector, xd: Vector) -> Scalar:
        """The power `xd . F(x, xd)` (non-positive)."""
        return jnp.dot(xd, self(x, xd))

    def __add__(self, other: "AbstractDissipation") -> "DissipationSum":
        if not isinstance(other, AbstractDissipation):
            return NotImplemented
        left = self.terms if isinstance(self, DissipationSum) else (self,)
        right = other.terms if isinstance(other, DissipationSum) else (other,)
        return DissipationSum(left + right)


def _joint_arrays(
    coordinates: Sequence[AbstractCoordinate], values: ArrayInput, name: str
) -> tuple[tuple[AbstractCoordinate, ...], Array]:
    coordinates = tuple(coordinates)
    for c in coordinates:
        if not isinstance(c, AbstractCoordinate):
            raise TypeError(f"expected joint coordinates, got {type(c).__name__}")
    values = jnp.broadcast_to(jnp.asarray(values, dtype=float), (len(coordinates),))
    return coordinates, values


def _joint_rates(coordinates, x, xd) -> tuple[Array, Array]:
    grads = jnp.stack([c.gradient(x) for c in coordinates], axis=1)
    return grads, grads.T @ xd


class JointDamping(AbstractDissipation):
    """Viscous joint damping: joint force `-b_j qd_j`, i.e. `F = -sum_j b_j grad q_j (grad q_j . xd)`.

    MuJoCo's joint `damping`.

    **Arguments:**

    - `coordinates`: the damped joint coordinates.
    - `damping`: `b_j` for each (N m s/rad or N s/m), shape `(len(coordinates),)` or a scalar;
      learnable.
    """

    coordinates: tuple[AbstractCoordinate, ...]
    damping: Float[Array, " p"]

    def __init__(self, coordinates: Sequence[AbstractCoordinate], damping: ArrayInput):
        self.coordinates, self.damping = _joint_arrays(coordinates, damping, "damping")

    def __call__(self, x: Vector, xd: Vector) -> Vector:
        grads, rates = _joint_rates(self.coordinates, x, xd)
        return -grads @ (self.damping * rates)


class JointQuadraticDamping(AbstractDissipation):
    """Quadratic (aerodynamic) joint damping: joint force `-c_j |qd_j| qd_j`, i.e.
    $F = -\\sum_j c_j \\nabla q_j\\, |\\dot q_j| \\dot q_j$ with $\\dot q_j = \\nabla q_j \\cdot \\dot x$.

    The drag of a paddle or a propeller turning with the joint: the resisting torque grows with the
    square of the speed. MuJoCo has no joint attribute for it.

    **Arguments:**

    - `coordinates`: the damped joint coordinates.
    - `damping`: `c_j` for each (N m s^2/rad^2 or N s^2/m^2), shape `(len(coordinates),)` or a
      scalar; learnable.

    !!! example

        ```python
        drag = cldyn.JointQuadraticDamping([cldyn.HingeAngle(child=(None, 0))], 0.02)
        system = cldyn.ConstrainedLagrangian(mass, potential, constraint, dissipation=drag)
        ```
    """

    coordinates: tuple[AbstractCoordinate, ...]
    damping: Float[Array, " p"]

    def __init__(self, coordinates: Sequence[AbstractCoordinate], damping: ArrayInput):
        self.coordinates, self.damping = _joint_arrays(coordinates, damping, "damping")

    def __call__(self, x: Vector, xd: Vector) -> Vector:
        grads, rates = _joint_rates(self.coordinates, x, xd)
        return -grads @ (self.damping * jnp.abs(rates) * rates)


class JointCoulomb(AbstractDissipation):
    """Smoothed Coulomb friction on joints: joint force `-f_j tanh(qd_j / v_s)`.

    MuJoCo's `frictionloss` is a hard friction constraint; the smooth `tanh` with a small velocity
    scale `v_s` keeps the dynamics differentiable and approaches it as `v_s -> 0`.

    **Arguments:**

    - `coordinates`: the joint coordinates with friction.
    - `friction`: the friction force or torque `f_j`, shape `(p,)` or a scalar; learnable.
    - `velocity_scale`: `v_s`, the joint speed below which friction is proportional to speed.
    """

    coordinates: tuple[AbstractCoordinate, ...]
    friction: Float[Array, " p"]
    velocity_scale: float = eqx.field(static=True)

    def __init__(
        self,
        coordinates: Sequence[AbstractCoordinate],
        friction: ArrayInput,
        *,
        velocity_scale: float = 0.05,
    ):
        if not velocity_scale > 0:
            raise ValueError(f"velocity_scale must be positive, got {velocity_scale}")
        self.coordinates, self.friction = _joint_arrays(coordinates, friction, "friction")
        self.velocity_scale = float(velocity_scale)

    def __call__(self, x: Vector, xd: Vector) -> Vector:
        grads, rates = _joint_rates(self.coordinates, x, xd)
        return -grads @ (self.friction * jnp.tanh(rates / self.velocity_scale))


class KeypointDrag(AbstractDissipation):
    """Drag on keypoints through the surrounding medium: `F_i = -(c1_i + c2_i |xd_i|) xd_i`.

    **Arguments:**

    - `linear`: linear drag coefficient per keypoint `c1` (N s/m), shape `(n_keypoints,)`; learnable.
    - `quadratic`: quadratic coefficient per keypoint `c2` (N s^2/m^2), same shape; learnable.
    - `dim`: dimension of each keypoint.
    """

    linear: Float[Array, " n_keypoints"]
    quadratic: Float[Array, " n_keypoints"]
    dim: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if jnp.shape(self.linear) != jnp.shape(self.quadratic) or jnp.ndim(self.linear) != 1:
            raise ValueError("linear and quadratic drag must both have shape (n_keypoints,)")

    def __call__(self, x: Vector, xd: Vector) -> Vector:
        v = xd.reshape(-1, self.dim)
        speed = jnp.sqrt(jnp.sum(v**2, axis=1) + jnp.finfo(xd.dtype).tiny)
        coefficient = self.linear + self.quadratic * speed
        return -(coefficient[:, None] * v).reshape(-1)


class DissipationSum(AbstractDissipation):
    """Several dissipative forces together; also what `F1 + F2` builds.

    **Arguments:**

    - `terms`: the forces to add.
    """

    terms: tuple[AbstractDissipation, ...]

    def __init__(self, terms: Sequence[AbstractDissipation]):
        terms = tuple(terms)
        for t in terms:
            if not isinstance(t, AbstractDissipation):
                raise TypeError(f"DissipationSum takes dissipations, got {type(t).__name__}")
        self.terms = terms

    def __call__(self, x: Vector, xd: Vector) -> Vector:
        total = jnp.zeros_like(xd)
        for t in self.terms:
            total = total + t(x, xd)
        return total
