"""The pieces `from_mjcf` builds a model from, as Equinox modules whose numbers are array fields.

Only the structure of a mechanism (which keypoint is which, which joint is a hinge, the order of the
groups) is static; every length, anchor, axis and offset is an array. The same scene built twice
therefore gives models with equal tree structure and equal static parts, and two scenes that differ
only in numbers (a link length, a mass) share one compiled program.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._constraint import AffineMap
from .._coordinates import AbstractCoordinate, wrap_angle
from .._custom_types import Scalar, Vector


def cmat(c: np.ndarray) -> np.ndarray:
    """Left multiplication by the complex number `c` as a 2x2 matrix."""
    return np.array([[c[0], -c[1]], [c[1], c[0]]])


@dataclasses.dataclass(frozen=True)
class Affine:
    """`y(x) = matrix @ x + const`, planar, in numpy while the model is being built: `matrix` `(2, k)`,
    `const` `(2,)`. `map()` turns it into the traced `AffineMap`."""

    matrix: np.ndarray
    const: np.ndarray

    def left(self, a: np.ndarray) -> "Affine":
        """`a @ y(x)` for a `(2, 2)` matrix `a`."""
        return Affine(a @ self.matrix, a @ self.const)

    def __add__(self, other: "Affine") -> "Affine":
        return Affine(self.matrix + other.matrix, self.const + other.const)

    def __sub__(self, other: "Affine") -> "Affine":
        return Affine(self.matrix - other.matrix, self.const - other.const)

    @property
    def is_constant(self) -> bool:
        return not np.any(self.matrix)

    def map(self) -> "AffineMap":
        return AffineMap(jnp.asarray(self.matrix, dtype=float), jnp.asarray(self.const, dtype=float))


def _fixed(offset: Array, dtype) -> Array:
    """A coordinate's offset (MuJoCo's `qpos0`): its convention, not a parameter (a spring's rest is the
    spring's own), so no gradient reaches it, as `HingeAngle`'s and `SliderPosition`'s are static."""
    return jax.lax.stop_gradient(offset.astype(dtype))


class FrameAngle(AbstractCoordinate):
    """A hinge angle read from two rigid groups' frames: `wrap(s * arg(z_child conj(z_parent)) - q0)`.

    Used where `HingeAngle` cannot express the hinge (its anchor is no keypoint).
    """

    child: AffineMap
    parent: AffineMap
    sign: float = eqx.field(static=True)
    offset: Float[Array, ""]

    def __call__(self, x: Vector) -> Scalar:
        zc, zp = self.child(x), self.parent(x)
        cross = zp[0] * zc[1] - zp[1] * zc[0]
        dot = zp[0] * zc[0] + zp[1] * zc[1]
        return wrap_angle(self.sign * jnp.arctan2(cross, dot) - _fixed(self.offset, x.dtype))


class FrameSlide(AbstractCoordinate):
    """A slide position read from frames: `q(x) = d(x) . u(x) - q0`, with `d` the displacement of the
    sliding keypoint from its reference point in the parent and `u` the slide axis, both affine.

    Used where `SliderPosition` cannot express the slide (a slide on a moving parent).
    """

    displacement: AffineMap
    axis: AffineMap
    offset: Float[Array, ""]

    def __call__(self, x: Vector) -> Scalar:
        return jnp.dot(self.displacement(x), self.axis(x)) - _fixed(self.offset, x.dtype)


def _rotation(angle: Array) -> Array:
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


class ForwardKinematics(eqx.Module):
    """`qpos -> x`: planar forward kinematics of a tree of hinges and slides, from its reference
    configuration.

    Group `i` (parents before children) turns about `anchors[i]` by `signs[i] * (qpos[a_i] - qpos0[i])`
    if it hangs on a hinge, or moves by `axes[i] * (qpos[a_i] - qpos0[i])` on a slide, relative to its
    parent; every keypoint moves with the group it was introduced in from its reference position.
    """

    parents: tuple[int, ...] = eqx.field(static=True)  # parent group index, -1 for the world
    hinges: tuple[bool, ...] = eqx.field(static=True)
    addresses: tuple[int, ...] = eqx.field(static=True)  # qpos address of each group's joint
    homes: tuple[int, ...] = eqx.field(static=True)  # group index of each keypoint
    anchors: Float[Array, "g 2"]
    axes: Float[Array, "g 2"]
    signs: Float[Array, " g"]
    qpos0: Float[Array, " g"]
    reference: Float[Array, "n 2"]

    def __call__(self, qpos: Float[Array, " m"]) -> Vector:
        dtype = qpos.dtype
        anchors, axes, signs = self.anchors.astype(dtype), self.axes.astype(dtype), self.signs.astype(dtype)
        qpos0, reference = self.qpos0.astype(dtype), self.reference.astype(dtype)
        angle = {-1: jnp.zeros((), dtype=dtype)}
        shift = {-1: jnp.zeros(2, dtype=dtype)}
        for g, (p, hinge, address) in enumerate(zip(self.parents, self.hinges, self.addresses)):
            dq = qpos[address] - qpos0[g]
            parent_rotation = _rotation(angle[p])
            if hinge:
                phi = signs[g] * dq
                angle[g] = angle[p] + phi
                shift[g] = parent_rotation @ (anchors[g] - _rotation(phi) @ anchors[g]) + shift[p]
            else:
                angle[g] = angle[p]
                shift[g] = parent_rotation @ (axes[g] * dq) + shift[p]
        points = [_rotation(angle[h]) @ reference[i] + shift[h] for i, h in enumerate(self.homes)]
        return jnp.concatenate(points)


class InverseKinematics(eqx.Module):
    """`x -> qpos`: every joint's coordinate read from the keypoints."""

    coordinates: tuple[AbstractCoordinate, ...]

    def __call__(self, x: Vector) -> Float[Array, " m"]:
        return jnp.stack([c(x) for c in self.coordinates])
