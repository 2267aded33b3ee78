"""Potential energies `V(x)` of the keypoints."""

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from ._constraint import static_point
from ._coordinates import AbstractCoordinate
from ._custom_types import ArrayInput, Scalar, Vector
from ._nn import keycld_mlp


class AbstractPotential(eqx.Module):
    """A potential energy `V(x)`; potentials add up with `+`."""

    @abc.abstractmethod
    def __call__(self, x: Vector) -> Scalar:
        """Evaluate `V(x)`.

        **Arguments:**

        - `x`: keypoint coordinates, shape `(k,)`.

        **Returns:** the potential energy, a scalar.
        """

    def gradient(self, x: Vector) -> Vector:
        """`grad V(x)`, shape `(k,)`; the conservative force is its negative."""
        return jax.grad(self.__call__)(x)

    def __add__(self, other: "AbstractPotential") -> "Sum":
        if not isinstance(other, AbstractPotential):
            return NotImplemented
        left = self.terms if isinstance(self, Sum) else (self,)
        right = other.terms if isinstance(other, Sum) else (other,)
        return Sum(left + right)


class Gravity(AbstractPotential):
    """Uniform gravity: $V(x) = g\\, w \\cdot x$.

    `w` holds, for every coordinate, the mass that its height carries: for point masses (KeyCLD) the
    keypoint masses on the vertical coordinates; for rigid bodies the weights from
    `rigid_body_gravity` and `pivot_body_gravity`, which place the weight at the true centre of mass.
    The weights are learnable.

    **Arguments:**

    - `weights`: shape `(k,)`.
    - `g`: gravitational acceleration, pointing along `-y`; 9.81 by default.

    !!! example

        ```python
        gravity = cldyn.Gravity.from_masses(jnp.array([1.0, 0.5]))  # V = g (y1 + 0.5 y2)
        ```
    """

    weights: Float[Array, " k"]
    g: float = eqx.field(static=True, default=9.81)

    def __check_init__(self):
        if jnp.ndim(self.weights) != 1:
            raise ValueError(f"Gravity weights must have shape (k,), got {jnp.shape(self.weights)}")

    @classmethod
    def from_masses(cls, masses: ArrayInput, *, g: float = 9.81, dim: int = 2) -> "Gravity":
        """Gravity on point masses, one per keypoint; the last coordinate of each is vertical."""
        masses = jnp.asarray(masses, dtype=float)
        weights = jnp.zeros((masses.shape[0], dim)).at[:, dim - 1].set(masses)
        return cls(weights.reshape(-1), g)

    def __call__(self, x: Vector) -> Scalar:
        return self.g * jnp.dot(self.weights, x)


class Spring(AbstractPotential):
    """A linear spring between two keypoints, or a keypoint and a fixed point.

    $V(x) = \\tfrac12 \\kappa (|x_i - x_j| - \\ell_0)^2$.

    **Arguments:**

    - `first`: index of the first keypoint.
    - `second`: index of the second keypoint, or `None` to attach to the fixed `point`.
    - `stiffness`: `kappa` (N/m); learnable.
    - `rest_length`: `ell_0` (m); learnable.
    - `point`: the fixed end when `second` is `None`; the origin by default.
    """

    first: int = eqx.field(static=True)
    second: int | None = eqx.field(static=True)
    stiffness: Float[Array, ""]
    rest_length: Float[Array, ""]
    point: tuple[float, float] = eqx.field(static=True)

    def __init__(
        self,
        first: int,
        second: int | None = None,
        *,
        stiffness: ArrayInput,
        rest_length: ArrayInput = 0.0,
        point: ArrayInput = (0.0, 0.0),
    ):
        if first == second:
            raise ValueError("a spring needs two different keypoints")
        self.first = int(first)
        self.second = None if second is None else int(second)
        self.stiffness = jnp.asarray(stiffness, dtype=float)
        self.rest_length = jnp.asarray(rest_length, dtype=float)
        self.point = static_point(point, 2, "point")

    def __call__(self, x: Vector) -> Scalar:
        a = x[2 * self.first : 2 * self.first + 2]
        if self.second is None:
            b = jnp.asarray(self.point, dtype=x.dtype)
        else:
            b = x[2 * self.second : 2 * self.second + 2]
        stretch = jnp.sqrt(jnp.sum((a - b) ** 2)) - self.rest_length
        return 0.5 * self.stiffness * stretch**2


class JointSpring(AbstractPotential):
    """A torsional or linear spring on a joint coordinate: $V = \\tfrac12 \\kappa (q(x) - q_0)^2$.

    MuJoCo's joint `stiffness` with `springref`. For a hinge, `q - q_0` is wrapped into
    `[-pi, pi)`.

    **Arguments:**

    - `coordinate`: the joint coordinate `q(x)`.
    - `stiffness`: `kappa` (N m/rad or N/m); learnable.
    - `rest`: `q_0`; learnable.
    - `periodic`: wrap `q - q_0` as an angle; true for hinges.
    """

    coordinate: AbstractCoordinate
    stiffness: Float[Array, ""]
    rest: Float[Array, ""]
    periodic: bool = eqx.field(static=True)

    def __init__(
        self,
        coordinate: AbstractCoordinate,
        *,
        stiffness: ArrayInput,
        rest: ArrayInput = 0.0,
        periodic: bool = True,
    ):
        self.coordinate = coordinate
        self.stiffness = jnp.asarray(stiffness, dtype=float)
        self.rest = jnp.asarray(rest, dtype=float)
        self.periodic = periodic

    def __call__(self, x: Vector) -> Scalar:
        delta = self.coordinate(x) - self.rest
        if self.periodic:
            delta = jnp.mod(delta + jnp.pi, 2 * jnp.pi) - jnp.pi
        return 0.5 * self.stiffness * delta**2


class MLPPotential(AbstractPotential):
    """A neural potential energy `V(x)`: KeyCLD appendix A.4.

    A multilayer perceptron with CELU activations (two hidden layers of 32 by default), weights
    initialised from `N(0, 0.01^2)` and zero biases.

    **Arguments:**

    - `size`: the number `k` of keypoint coordinates.
    - `width`: hidden width.
    - `depth`: number of hidden layers.
    - `key`: a `jax.random` key.
    """

    mlp: eqx.nn.MLP

    def __init__(self, size: int, *, width: int = 32, depth: int = 2, key: PRNGKeyArray):
        if size <= 0 or width <= 0 or depth < 0:
            raise ValueError(f"need size > 0, width > 0, depth >= 0; got {size}, {width}, {depth}")
        self.mlp = keycld_mlp(size, "scalar", width, depth, key=key)

    def __call__(self, x: Vector) -> Scalar:
        return self.mlp(x)


class Sum(AbstractPotential):
    """The sum of several potentials; also what `V1 + V2` builds.

    **Arguments:**

    - `terms`: the potentials to add.
    """

    terms: tuple[AbstractPotential, ...]

    def __init__(self, terms: Sequence[AbstractPotential]):
        terms = tuple(terms)
        for t in terms:
            if not isinstance(t, AbstractPotential):
                raise TypeError(f"Sum takes potentials, got {type(t).__name__}")
        self.terms = terms

    def __call__(self, x: Vector) -> Scalar:
        total = jnp.zeros((), dtype=x.dtype)
        for t in self.terms:
            total = total + t(x)
        return total
