"""Joint coordinates as functions of the keypoints.

A hinge angle or a slider position `q(x)` turns joint-space effects into Cartesian forces: an actuator
acts through `g(x) = grad q(x)`, viscous damping `b` gives `-b grad q (grad q . xd)`, a joint spring
`-k (q - q0) grad q`. One mechanism serves actuators, damping, friction and springs.
"""

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._constraint import static_point
from ._custom_types import ArrayInput, Scalar, Vector

_DIM = 2


def wrap_angle(angle: ArrayInput) -> Array:
    """Wrap an angle into `[-pi, pi)`.

    **Arguments:**

    - `angle`: an angle or array of angles, in radians.

    **Returns:** the same angles, shifted by multiples of `2 pi` into `[-pi, pi)`.
    """
    return jnp.mod(jnp.asarray(angle) + jnp.pi, 2 * jnp.pi) - jnp.pi


class AbstractCoordinate(eqx.Module):
    """A scalar joint coordinate `q(x)` of the keypoints."""

    @abc.abstractmethod
    def __call__(self, x: Vector) -> Scalar:
        """Evaluate `q(x)`.

        **Arguments:**

        - `x`: keypoint coordinates, shape `(k,)`.

        **Returns:** the joint coordinate, a scalar.
        """

    def gradient(self, x: Vector) -> Vector:
        """`grad q(x)`, shape `(k,)`: the direction in which a joint force acts on the keypoints."""
        return jax.grad(self.__call__)(x)

    def rate(self, x: Vector, xd: Vector) -> Scalar:
        """The joint velocity `qd = grad q(x) . xd`."""
        return jax.jvp(self.__call__, (x,), (xd,))[1]


def _segment(
    x: Vector, segment: tuple[int | None, int | None], pivot: tuple[float, ...]
) -> Array:
    def point(index):
        if index is None:
            return jnp.asarray(pivot, dtype=x.dtype)
        return x[_DIM * index : _DIM * (index + 1)]

    tail, head = segment
    return point(head) - point(tail)


def _check_segment(name: str, segment) -> tuple[int | None, int | None]:
    segment = tuple(segment)
    if len(segment) != 2 or segment[0] == segment[1]:
        raise ValueError(f"{name} must be a (tail, head) pair of distinct points, got {segment}")
    for i in segment:
        if i is not None and (not isinstance(i, int | np.integer) or i < 0):
            raise ValueError(f"{name} holds {i!r}: use keypoint indices >= 0, or None for the pivot")
    return tuple(None if i is None else int(i) for i in segment)


class HingeAngle(AbstractCoordinate):
    """The angle of a planar hinge, from keypoint segments.

    $q(x) = \\mathrm{wrap}(s\\,\\angle(r, c) - q_0)$, where the child direction `c` points from
    `child[0]` to `child[1]` and the parent direction `r` from `parent[0]` to `parent[1]` (or is the
    fixed `reference` direction when `parent` is `None`). In a segment, `None` stands for the fixed
    point `pivot`. The angle is counter-clockwise in the `(x, y)` plane for `sign = 1`.

    **Arguments:**

    - `child`: `(tail, head)` keypoint indices of a segment fixed in the child body.
    - `parent`: `(tail, head)` of a segment fixed in the parent body, or `None` if the parent is
      the world.
    - `pivot`: the fixed point used where a segment names `None`; the origin by default.
    - `reference`: the world direction from which the angle is measured when `parent` is `None`;
      straight down `(0, -1)` by default, so a hanging pendulum is at angle 0.
    - `sign`: `1` for counter-clockwise positive, `-1` for clockwise (a MuJoCo hinge whose axis
      points into the plane).
    - `offset`: subtracted from the angle, to match another convention (MuJoCo's `qpos0`).

    !!! example

        ```python
        shoulder = cldyn.HingeAngle(child=(None, 0))              # link 1 vs. straight down
        elbow = cldyn.HingeAngle(child=(0, 1), parent=(None, 0))  # link 2 vs. link 1
        ```
    """

    child: tuple[int | None, int | None] = eqx.field(static=True)
    parent: tuple[int | None, int | None] | None = eqx.field(static=True)
    pivot: tuple[float, float] = eqx.field(static=True)
    reference: tuple[float, float] = eqx.field(static=True)
    sign: float = eqx.field(static=True)
    offset: float = eqx.field(static=True)

    def __init__(
        self,
        child: tuple[int | None, int | None],
        parent: tuple[int | None, int | None] | None = None,
        *,
        pivot: ArrayInput = (0.0, 0.0),
        reference: ArrayInput = (0.0, -1.0),
        sign: float = 1.0,
        offset: float = 0.0,
    ):
        self.child = _check_segment("child", child)
        self.parent = None if parent is None else _check_segment("parent", parent)
        if float(sign) not in (1.0, -1.0):
            raise ValueError(f"sign must be +1 or -1, got {sign}")
        self.pivot = static_point(pivot, 2, "pivot")
        self.reference = static_point(reference, 2, "reference")
        if not any(self.reference):
            raise ValueError("reference must be a non-zero direction")
        self.sign = float(sign)
        self.offset = float(offset)

    def __call__(self, x: Vector) -> Scalar:
        c = _segment(x, self.child, self.pivot)
        if self.parent is None:
            r = jnp.asarray(self.reference, dtype=x.dtype)
        else:
            r = _segment(x, self.parent, self.pivot)
        cross = r[0] * c[1] - r[1] * c[0]
        dot = r[0] * c[0] + r[1] * c[1]
        return wrap_angle(self.sign * jnp.arctan2(cross, dot) - self.offset)


class SliderPosition(AbstractCoordinate):
    """The position of a keypoint along a fixed line: $q(x) = a \\cdot (x_i - o) - q_0$.

    **Arguments:**

    - `keypoint`: index of the sliding keypoint.
    - `axis`: direction `a` of the slide (normalised here); `(1, 0)` by default.
    - `origin`: a point `o` on the line; the origin by default.
    - `offset`: `q_0`, subtracted from the position.

    !!! example

        ```python
        cart = cldyn.SliderPosition(0)  # horizontal position of keypoint 0
        ```
    """

    keypoint: int = eqx.field(static=True)
    axis: tuple[float, float] = eqx.field(static=True)
    origin: tuple[float, float] = eqx.field(static=True)
    offset: float = eqx.field(static=True)

    def __init__(
        self,
        keypoint: int,
        *,
        axis: ArrayInput = (1.0, 0.0),
        origin: ArrayInput = (0.0, 0.0),
        offset: float = 0.0,
    ):
        if not isinstance(keypoint, int | np.integer) or keypoint < 0:
            raise ValueError(f"keypoint must be an index >= 0, got {keypoint!r}")
        axis = np.asarray(static_point(axis, 2, "axis"))
        norm = float(np.linalg.norm(axis))
        if norm == 0.0:
            raise ValueError("axis must be a non-zero direction")
        self.keypoint = int(keypoint)
        self.axis = tuple(float(v) for v in axis / norm)
        self.origin = static_point(origin, 2, "origin")
        self.offset = float(offset)

    def __call__(self, x: Vector) -> Scalar:
        p = x[_DIM * self.keypoint : _DIM * (self.keypoint + 1)]
        axis = jnp.asarray(self.axis, dtype=x.dtype)
        return jnp.dot(axis, p - jnp.asarray(self.origin, dtype=x.dtype)) - self.offset


class JointMap(eqx.Module):
    """The map between minimal joint coordinates `q` and keypoint coordinates `x = F(q)`.

    Systems with a kinematic tree come with one (KeyCLD eq. 7); closed loops such as the four-bar
    linkage have none. Velocities map through the Jacobians: `xd = DF(q) qd`, `qd = Dq(x) xd`.

    **Arguments:**

    - `forward`: `F(q)`, from `(m,)` joint coordinates to `(k,)` keypoint coordinates.
    - `inverse`: `q(x)`, its inverse on the constraint manifold.
    - `names`: a name for each joint coordinate.

    `forward` and `inverse` may be plain functions or Equinox modules; a module's arrays stay arrays of
    the map (not constants baked into a compiled program), so maps that differ only in numbers share
    one compilation.
    """

    forward: Callable
    inverse: Callable
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def num_joints(self) -> int:
        """The number `m` of joint coordinates."""
        return len(self.names)

    def keypoints(self, q: Float[Array, " m"]) -> Vector:
        """`x = F(q)`."""
        return self.forward(jnp.asarray(q, dtype=float))

    def joints(self, x: Vector) -> Float[Array, " m"]:
        """`q(x)`."""
        return self.inverse(jnp.asarray(x, dtype=float))

    def to_keypoints(
        self, q: Float[Array, " m"], qd: Float[Array, " m"]
    ) -> tuple[Vector, Vector]:
        """`(x, xd) = (F(q), DF(q) qd)`."""
        q = jnp.asarray(q, dtype=float)
        qd = jnp.asarray(qd, dtype=float)
        if q.shape != (self.num_joints,) or qd.shape != (self.num_joints,):
            raise ValueError(
                f"q and qd must have shape ({self.num_joints},), got {q.shape} and {qd.shape}"
            )
        return jax.jvp(self.forward, (q,), (qd,))

    def to_joints(self, x: Vector, xd: Vector) -> tuple[Float[Array, " m"], Float[Array, " m"]]:
        """`(q, qd) = (q(x), Dq(x) xd)`."""
        x = jnp.asarray(x, dtype=float)
        xd = jnp.asarray(xd, dtype=float)
        if x.shape != xd.shape or x.ndim != 1:
            raise ValueError(f"x and xd must have the same shape (k,), got {x.shape}, {xd.shape}")
        return jax.jvp(self.inverse, (x,), (xd,))
