"""Holonomic constraints `Phi(x) = const` on the keypoint coordinates (KeyCLD section 2).

Only the Jacobian `DPhi` and the curvature term `<D2Phi, xd> xd` enter the equations of motion (eq. 6),
so constants such as lengths never need to be known: a constraint states *which* quantity is
conserved, and the integrator keeps it at its initial value.
"""

import abc
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._custom_types import ArrayInput, Vector


class AbstractConstraint(eqx.Module):
    """A vector of holonomic constraints `Phi: R^k -> R^n`, conserved along the motion.

    Subclasses implement `__call__` and `num_constraints`. The Jacobian and the curvature term are
    derived by automatic differentiation.
    """

    @property
    @abc.abstractmethod
    def num_constraints(self) -> int:
        """The number `n` of scalar constraints."""

    @abc.abstractmethod
    def __call__(self, x: Vector) -> Float[Array, " n"]:
        """Evaluate `Phi(x)`.

        **Arguments:**

        - `x`: keypoint coordinates, shape `(k,)`.

        **Returns:** the constraint values, shape `(n,)`.
        """

    def jacobian(self, x: Vector) -> Float[Array, "n k"]:
        """The constraint Jacobian `DPhi(x)`, shape `(n, k)`."""
        return jax.jacfwd(self.__call__)(x)

    def velocity(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        """The constraint velocity `d/dt Phi = DPhi(x) xd`, without forming `DPhi`."""
        return jax.jvp(self.__call__, (x,), (xd,))[1]

    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        """The curvature term `<D2Phi(x), xd> xd = d/dt (DPhi(x)) xd` of eq. 6.

        Computed as the JVP along `xd` of `x -> DPhi(x) xd`: two forward passes, never the
        `(n, k, k)` Hessian tensor.
        """
        return jax.jvp(lambda y: self.velocity(y, xd), (x,), (xd,))[1]


def _point_slice(index: int, dim: int) -> slice:
    return slice(dim * index, dim * (index + 1))


def static_point(value: ArrayInput, dim: int, name: str) -> tuple[float, ...]:
    """A fixed point or direction, kept as hashable configuration rather than a trainable array."""
    array = np.asarray(value, dtype=float)
    if array.shape != (dim,):
        raise ValueError(f"{name} must have shape ({dim},), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got {array}")
    return tuple(float(v) for v in array)


def _check_index(name: str, index: int) -> None:
    if not isinstance(index, int | np.integer) or index < 0:
        raise ValueError(f"{name} must be a non-negative keypoint index, got {index!r}")


class Distance(AbstractConstraint):
    """Two keypoints at a fixed distance: `Phi(x) = |x_i - x_j|`.

    The multiplier of this constraint is the tension along the segment, in newtons. The
    Jacobian is undefined when the two keypoints coincide.

    **Arguments:**

    - `first`, `second`: indices of the two keypoints.
    - `dim`: dimension of each keypoint (2 for planar systems).

    !!! example

        ```python
        rod = cldyn.Distance(0, 1)  # keypoints 0 and 1 are joined by a rigid rod
        ```
    """

    first: int = eqx.field(static=True)
    second: int = eqx.field(static=True)
    dim: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        _check_index("first", self.first)
        _check_index("second", self.second)
        if self.first == self.second:
            raise ValueError(f"Distance needs two different keypoints, got {self.first} twice")

    @property
    def num_constraints(self) -> int:
        return 1

    def __call__(self, x: Vector) -> Float[Array, " 1"]:
        delta = x[_point_slice(self.first, self.dim)] - x[_point_slice(self.second, self.dim)]
        return jnp.sqrt(jnp.sum(delta**2))[None]


class Anchor(AbstractConstraint):
    """A keypoint at a fixed distance from a fixed point: `Phi(x) = |x_i - p|`.

    A pendulum bob, or the first link of a chain, pivoting about `point`.

    **Arguments:**

    - `keypoint`: index of the keypoint.
    - `point`: the fixed point, shape `(dim,)`; the origin by default.
    - `dim`: dimension of each keypoint.
    """

    keypoint: int = eqx.field(static=True)
    point: tuple[float, ...] = eqx.field(static=True)
    dim: int = eqx.field(static=True)

    def __init__(self, keypoint: int, point: ArrayInput | None = None, *, dim: int = 2):
        _check_index("keypoint", keypoint)
        self.keypoint = int(keypoint)
        self.dim = dim
        self.point = static_point(np.zeros(dim) if point is None else point, dim, "Anchor point")

    @property
    def num_constraints(self) -> int:
        return 1

    def __call__(self, x: Vector) -> Float[Array, " 1"]:
        delta = x[_point_slice(self.keypoint, self.dim)] - jnp.asarray(self.point)
        return jnp.sqrt(jnp.sum(delta**2))[None]


class FixedCoordinate(AbstractConstraint):
    """One coordinate of a keypoint is constant: `Phi(x) = x_i[axis]`.

    A cart on a horizontal rail is `FixedCoordinate(cart, axis=1)`.

    **Arguments:**

    - `keypoint`: index of the keypoint.
    - `axis`: which coordinate of that keypoint is fixed (0 is x, 1 is y).
    - `dim`: dimension of each keypoint.
    """

    keypoint: int = eqx.field(static=True)
    axis: int = eqx.field(static=True)
    dim: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        _check_index("keypoint", self.keypoint)
        if not 0 <= self.axis < self.dim:
            raise ValueError(f"axis must be in [0, {self.dim}), got {self.axis}")

    @property
    def num_constraints(self) -> int:
        return 1

    def __call__(self, x: Vector) -> Float[Array, " 1"]:
        return x[self.dim * self.keypoint + self.axis][None]


class Stack(AbstractConstraint):
    """Several constraints together: `Phi(x) = [Phi_1(x), Phi_2(x), ...]`.

    **Arguments:**

    - `constraints`: the constraints to concatenate, in order.

    !!! example

        ```python
        acrobot = cldyn.Stack([cldyn.Anchor(0), cldyn.Distance(0, 1)])
        ```
    """

    constraints: tuple[AbstractConstraint, ...]

    def __init__(self, constraints: Sequence[AbstractConstraint]):
        constraints = tuple(constraints)
        for c in constraints:
            if not isinstance(c, AbstractConstraint):
                raise TypeError(f"Stack takes constraints, got {type(c).__name__}")
        self.constraints = constraints

    @property
    def num_constraints(self) -> int:
        return sum(c.num_constraints for c in self.constraints)

    def __call__(self, x: Vector) -> Float[Array, " n"]:
        if not self.constraints:
            return jnp.zeros(0, dtype=x.dtype)
        return jnp.concatenate([c(x) for c in self.constraints])


class FromFunction(AbstractConstraint):
    """Any user-supplied constraint function `Phi(x)`.

    **Arguments:**

    - `fn`: a function from keypoint coordinates `(k,)` to constraint values `(n,)`. It must be
      differentiable twice by JAX.
    - `num_constraints`: the length `n` of its output.

    !!! example

        ```python
        # keypoint 0 slides along the line y = x
        line = cldyn.FromFunction(lambda x: (x[1] - x[0])[None], num_constraints=1)
        ```
    """

    fn: Callable[[Vector], Float[Array, " n"]] = eqx.field(static=True)
    size: int = eqx.field(static=True)

    def __init__(self, fn: Callable[[Vector], Float[Array, " n"]], num_constraints: int):
        if not callable(fn):
            raise TypeError("FromFunction needs a callable Phi(x)")
        if num_constraints < 0:
            raise ValueError(f"num_constraints must be >= 0, got {num_constraints}")
        self.fn = fn
        self.size = int(num_constraints)

    @property
    def num_constraints(self) -> int:
        return self.size

    def __call__(self, x: Vector) -> Float[Array, " n"]:
        out = jnp.atleast_1d(self.fn(x))
        if out.shape != (self.size,):
            raise ValueError(
                f"FromFunction: Phi(x) returned shape {out.shape}, "
                f"but num_constraints={self.size} was declared"
            )
        return out
