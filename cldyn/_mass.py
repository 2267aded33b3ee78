"""Constant mass matrices in Cartesian keypoint coordinates (KeyCLD eq. 3, 14, appendix A.3).

In keypoint coordinates the mass matrix does not depend on the state: that is the point of the
method. `PointMasses` is KeyCLD's diagonal matrix; `ConstantMass` is any symmetric positive definite
matrix, which with the rigid-body blocks below reproduces a planar multibody system exactly.
"""

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._custom_types import ArrayInput, Matrix, Scalar, Vector
from ._linalg import small_matmul


class AbstractMass(eqx.Module):
    """A constant symmetric positive definite mass matrix `M`, shape `(k, k)`."""

    @property
    @abc.abstractmethod
    def size(self) -> int:
        """The number `k` of keypoint coordinates."""

    @abc.abstractmethod
    def matrix(self) -> Matrix:
        """The dense mass matrix `M`, shape `(k, k)`."""

    @abc.abstractmethod
    def matvec(self, v: Float[Array, "k ..."]) -> Float[Array, "k ..."]:
        """`M v` for a vector or a matrix `v`."""

    @abc.abstractmethod
    def solve(self, b: Float[Array, "k ..."]) -> Float[Array, "k ..."]:
        """`M^-1 b` for a vector or a matrix `b`."""

    @abc.abstractmethod
    def inverse(self) -> Matrix:
        """The dense inverse `M^-1`, shape `(k, k)`."""

    def kinetic_energy(self, xd: Vector) -> Scalar:
        """`T = 1/2 xd^T M xd` (eq. 3 in Cartesian coordinates)."""
        return 0.5 * jnp.dot(xd, self.matvec(xd))


def _positive_masses(masses: ArrayInput) -> Array:
    """Keypoint masses as a float array of shape `(n_keypoints,)`, all positive, or a ValueError."""
    masses = jnp.asarray(masses, dtype=float)
    if masses.ndim != 1 or masses.shape[0] == 0:
        raise ValueError(f"masses must have shape (n_keypoints,), got {masses.shape}")
    if not isinstance(masses, jax.core.Tracer) and not bool(jnp.all(masses > 0)):
        raise ValueError(f"keypoint masses must be positive, got {np.asarray(masses)}")
    return masses


class PointMasses(AbstractMass):
    """One point mass per keypoint: KeyCLD's diagonal mass matrix (eq. 14).

    The masses are stored as their square roots and squared on use, so gradient steps keep them
    positive.

    **Arguments:**

    - `masses`: the mass of each keypoint, shape `(n_keypoints,)`, all positive.
    - `dim`: dimension of each keypoint.

    !!! example

        ```python
        mass = cldyn.PointMasses(jnp.array([1.0, 0.5]))  # two planar keypoints, k = 4
        ```
    """

    sqrt_masses: Float[Array, " n_keypoints"]
    dim: int = eqx.field(static=True)

    def __init__(self, masses: ArrayInput, *, dim: int = 2):
        self.sqrt_masses = jnp.sqrt(_positive_masses(masses))
        self.dim = dim

    @property
    def masses(self) -> Float[Array, " n_keypoints"]:
        """The keypoint masses."""
        return self.sqrt_masses**2

    @property
    def size(self) -> int:
        return self.dim * self.sqrt_masses.shape[0]

    def diagonal(self) -> Vector:
        """The diagonal of `M`, shape `(k,)`."""
        return jnp.repeat(self.masses, self.dim)

    def matrix(self) -> Matrix:
        return jnp.diag(self.diagonal())

    def matvec(self, v):
        d = self.diagonal()
        return d * v if v.ndim == 1 else d[:, None] * v

    def solve(self, b):
        d = self.diagonal()
        return b / d if b.ndim == 1 else b / d[:, None]

    def inverse(self) -> Matrix:
        return jnp.diag(1.0 / self.diagonal())


class CoupledMasses(AbstractMass):
    """A learnable constant mass matrix that couples keypoints: $M = A \\otimes I_d$.

    `A` is a symmetric positive definite `(n, n)` matrix over the `n` keypoints, stored as its
    Cholesky factor (log-diagonal and strictly lower part), so every parameter value is valid. With a
    diagonal `A` this is KeyCLD's `PointMasses` (eq. 14); the off-diagonal terms give the exact
    kinetic energy of a planar rigid body carried by two keypoints whose centre of mass lies on the
    line between them (`T = 1/2 m |v_c|^2 + 1/2 I |omega|^2` with `v_c` an affine combination of the
    two keypoint velocities), which point masses at, say, both ends of a uniform rod cannot express.

    **Arguments:**

    - `masses`: the initial keypoint masses (the diagonal of `A`), shape `(n,)`.
    - `dim`: dimension of each keypoint.

    !!! example

        ```python
        mass = cldyn.CoupledMasses(jnp.ones(2))   # two planar keypoints, k = 4, initially diagonal
        ```
    """

    log_diagonal: Float[Array, " n"]
    lower: Float[Array, "n n"]
    dim: int = eqx.field(static=True)

    def __init__(self, masses: ArrayInput, *, dim: int = 2):
        masses = _positive_masses(masses)
        self.log_diagonal = 0.5 * jnp.log(masses)
        self.lower = jnp.zeros((masses.shape[0], masses.shape[0]), dtype=masses.dtype)
        self.dim = dim

    @property
    def size(self) -> int:
        return self.dim * self.log_diagonal.shape[0]

    def keypoint_matrix(self) -> Float[Array, "n n"]:
        """The `(n, n)` matrix `A` over keypoints."""
        factor = jnp.tril(self.lower, -1) + jnp.diag(jnp.exp(self.log_diagonal))
        return factor @ factor.T

    def matrix(self) -> Matrix:
        return jnp.kron(self.keypoint_matrix(), jnp.eye(self.dim, dtype=self.lower.dtype))

    def _apply(self, a, v):
        n = a.shape[0]
        shaped = v.reshape(n, self.dim, *v.shape[1:])
        return jnp.tensordot(a, shaped, axes=1).reshape(v.shape)

    def matvec(self, v):
        return self._apply(self.keypoint_matrix(), v)

    def solve(self, b):
        return self._apply(jnp.linalg.inv(self.keypoint_matrix()), b)

    def inverse(self) -> Matrix:
        return jnp.kron(jnp.linalg.inv(self.keypoint_matrix()), jnp.eye(self.dim, dtype=self.lower.dtype))


class ConstantMass(AbstractMass):
    """Any constant symmetric positive definite mass matrix, Cholesky-parameterised.

    `M = L L^T` with `L` lower triangular and a positive diagonal stored by its logarithm, so that
    every parameter value gives a valid mass matrix.

    **Arguments:**

    - `matrix`: the mass matrix, shape `(k, k)`, symmetric positive definite.

    !!! example

        ```python
        block = cldyn.rigid_body_mass(1.0, 0.02, com=[0.5, 0.0], points=[[0, 0], [1, 0]])
        mass = cldyn.ConstantMass(block)
        ```
    """

    strict_lower: Float[Array, "k k"]
    log_diagonal: Float[Array, " k"]

    def __init__(self, matrix: ArrayInput):
        matrix = jnp.asarray(matrix, dtype=float)
        if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or matrix.shape[0] == 0:
            raise ValueError(f"mass matrix must be square (k, k), got shape {matrix.shape}")
        if not isinstance(matrix, jax.core.Tracer):
            m = np.asarray(matrix)
            if not np.allclose(m, m.T, rtol=1e-10, atol=1e-12 * np.abs(m).max()):
                raise ValueError("mass matrix must be symmetric")
            smallest = float(np.linalg.eigvalsh(0.5 * (m + m.T)).min())
            if not smallest > 0:
                raise ValueError(
                    f"mass matrix must be positive definite; its smallest eigenvalue is "
                    f"{smallest:.3g}. Does every keypoint carry mass (or inertia)?"
                )
        lower = jnp.linalg.cholesky(0.5 * (matrix + matrix.T))
        self.strict_lower = jnp.tril(lower, -1)
        self.log_diagonal = jnp.log(jnp.diagonal(lower))

    @classmethod
    def from_blocks(
        cls,
        blocks: Sequence[tuple[Sequence[int], ArrayInput]],
        num_keypoints: int,
        *,
        dim: int = 2,
    ) -> "ConstantMass":
        """Assemble a mass matrix from per-body blocks.

        **Arguments:**

        - `blocks`: pairs `(keypoints, block)`; `block` has shape `(dim * len(keypoints),) * 2` and
          acts on those keypoints' velocities, in that order. Blocks that share keypoints add up.
        - `num_keypoints`: the total number of keypoints.
        - `dim`: dimension of each keypoint.

        **Returns:** a `ConstantMass` of size `dim * num_keypoints`.
        """
        return cls(assemble_blocks(blocks, num_keypoints, dim=dim))

    def cholesky(self) -> Float[Array, "k k"]:
        """The lower Cholesky factor `L` of `M = L L^T`."""
        return self.strict_lower + jnp.diag(jnp.exp(self.log_diagonal))

    @property
    def size(self) -> int:
        return self.log_diagonal.shape[0]

    def matrix(self) -> Matrix:
        lower = self.cholesky()
        return lower @ lower.T

    def matvec(self, v):
        lower = self.cholesky()
        return lower @ (lower.T @ v)

    def inverse(self) -> Matrix:
        eye = jnp.eye(self.size, dtype=self.log_diagonal.dtype)
        return jax.scipy.linalg.cho_solve((self.cholesky(), True), eye)

    def solve(self, b):
        # M is tiny and shared by every state in a batch: one dense inverse, then a matmul that
        # vectorises, beats a triangular solve per state.
        return small_matmul(self.inverse(), b)


def assemble_blocks(
    blocks: Sequence[tuple[Sequence[int], ArrayInput]], num_keypoints: int, *, dim: int = 2
) -> Float[Array, "k k"]:
    """Add per-body blocks into a `(k, k)` matrix (see `ConstantMass.from_blocks`)."""
    k = dim * num_keypoints
    out = jnp.zeros((k, k))
    for keypoints, block in blocks:
        idx = np.concatenate([np.arange(dim * i, dim * (i + 1)) for i in keypoints])
        block = jnp.asarray(block, dtype=float)
        if block.shape != (idx.size, idx.size):
            raise ValueError(
                f"block for keypoints {tuple(keypoints)} must have shape "
                f"({idx.size}, {idx.size}), got {block.shape}"
            )
        if np.any(idx >= k):
            raise ValueError(f"keypoints {tuple(keypoints)} out of range for {num_keypoints}")
        out = out.at[np.ix_(idx, idx)].add(block)
    return out


def _rotate90(v: Array) -> Array:
    return jnp.stack([-v[..., 1], v[..., 0]], axis=-1)


def body_frame(com: ArrayInput, points: ArrayInput) -> tuple[Array, Array, Array]:
    """Coefficients `(a, b)` such that `com = p1 + a r + b R90 r` with `r = p2 - p1`, and `|r|^2`.

    The centre of mass of a planar rigid body is a fixed linear combination of any two distinct
    points of the body; this is what makes the mass block constant.
    """
    points = jnp.asarray(points, dtype=float)
    com = jnp.asarray(com, dtype=float)
    if points.shape != (2, 2) or com.shape != (2,):
        raise ValueError(
            f"points must have shape (2, 2) and com shape (2,), got {points.shape}, {com.shape}"
        )
    r = points[1] - points[0]
    length2 = jnp.dot(r, r)
    if not isinstance(length2, jax.core.Tracer) and not float(length2) > 0:
        raise ValueError("the two points carrying a rigid body must be distinct")
    rel = com - points[0]
    a = jnp.dot(rel, r) / length2
    b = (r[0] * rel[1] - r[1] * rel[0]) / length2
    return a, b, length2


def _com_map(a, b):
    eye = jnp.eye(2)
    rot = jnp.array([[0.0, -1.0], [1.0, 0.0]])
    # v_com = [(1 - a) I - b R90, a I + b R90] [xd1; xd2]
    return jnp.concatenate([(1 - a) * eye - b * rot, a * eye + b * rot], axis=1)


def rigid_body_mass(
    mass: ArrayInput, inertia: ArrayInput, com: ArrayInput, points: ArrayInput
) -> Float[Array, "4 4"]:
    """The exact constant mass block of a planar rigid body carried by two keypoints.

    With `r = x2 - x1` of constant length `L`, the centre of mass is `c = x1 + a r + b R90 r` for
    fixed `(a, b)` (it may lie off the line between the keypoints), and the angular velocity
    satisfies `omega^2 L^2 = |rd|^2`, so
    $T = \\tfrac12 m |\\dot c|^2 + \\tfrac12 (I / L^2) |\\dot x_2 - \\dot x_1|^2$
    is a constant quadratic form in `(xd1, xd2)`.

    **Arguments:**

    - `mass`: the body's mass `m`.
    - `inertia`: its rotational inertia `I` about its centre of mass (about the axis normal to the
      plane).
    - `com`: its centre of mass, shape `(2,)`, in the same frame as `points`.
    - `points`: positions of the two carrying keypoints in that frame, shape `(2, 2)`.

    **Returns:** the `(4, 4)` block acting on `[xd1, xd2]`.

    !!! example

        ```python
        # uniform rod of length 1 between keypoints 0 and 1
        block = cldyn.rigid_body_mass(1.0, 1 / 12, com=[0.5, 0], points=[[0, 0], [1, 0]])
        mass = cldyn.ConstantMass.from_blocks([((0, 1), block)], num_keypoints=2)
        ```
    """
    a, b, length2 = body_frame(com, points)
    com_map = _com_map(a, b)
    spin = jnp.concatenate([-jnp.eye(2), jnp.eye(2)], axis=1)
    return mass * com_map.T @ com_map + (inertia / length2) * spin.T @ spin


def pivot_body_mass(
    mass: ArrayInput, inertia: ArrayInput, com: ArrayInput, pivot: ArrayInput, point: ArrayInput
) -> Float[Array, "2 2"]:
    """The exact constant mass block of a planar rigid body pivoting about a fixed point.

    The body is carried by a single keypoint `x1`; the pivot does not move, so this is the lower
    right block of `rigid_body_mass` with the pivot as first point.

    **Arguments:**

    - `mass`, `inertia`: as in `rigid_body_mass`.
    - `com`: the centre of mass, shape `(2,)`.
    - `pivot`: the fixed point, shape `(2,)`.
    - `point`: the position of the keypoint, shape `(2,)`, in the same frame.

    **Returns:** the `(2, 2)` block acting on `xd1`.
    """
    points = jnp.stack([jnp.asarray(pivot, dtype=float), jnp.asarray(point, dtype=float)])
    return rigid_body_mass(mass, inertia, com, points)[2:, 2:]


def rigid_body_gravity(mass: ArrayInput, com: ArrayInput, points: ArrayInput) -> Float[Array, " 4"]:
    """Gravity weights of a rigid body carried by two keypoints, for `Gravity`.

    The height of the centre of mass is linear in the keypoints, `c_y = w . [x1, x2] / m`; this
    returns `w = m * dc_y / d[x1, x2]`, so that the body's potential is `g w . [x1, x2]` up to a
    constant.

    **Arguments:**

    - `mass`: the body's mass.
    - `com`, `points`: as in `rigid_body_mass`.

    **Returns:** weights of shape `(4,)` on `[x1, x2]`.
    """
    a, b, _ = body_frame(com, points)
    return mass * _com_map(a, b)[1]


def pivot_body_gravity(
    mass: ArrayInput, com: ArrayInput, pivot: ArrayInput, point: ArrayInput
) -> Float[Array, " 2"]:
    """Gravity weights of a body pivoting about a fixed point, carried by one keypoint.

    **Arguments:** as in `pivot_body_mass`, without the inertia.

    **Returns:** weights of shape `(2,)` on the keypoint.
    """
    points = jnp.stack([jnp.asarray(pivot, dtype=float), jnp.asarray(point, dtype=float)])
    return rigid_body_gravity(mass, com, points)[2:]


class JointArmature(eqx.Module):
    """Rotor inertia reflected onto joints (MuJoCo's `armature`).

    Adds $\\tfrac12 \\sum_j a_j \\dot q_j^2$ to the kinetic energy, with $\\dot q_j = \\nabla q_j \\cdot
    \\dot x$. Unlike the body masses this term depends on `x`, so it contributes the mass
    $\\sum_j a_j \\nabla q_j \\nabla q_j^T$ and the velocity-product force
    $-\\sum_j a_j \\nabla q_j\\, (\\dot x^T D^2 q_j\\, \\dot x)$ to the equations of motion.

    **Arguments:**

    - `coordinates`: the joint coordinates.
    - `armature`: `a_j` for each (kg m^2 or kg), shape `(p,)` or a scalar; learnable.
    """

    coordinates: tuple
    armature: Float[Array, " p"]

    def __init__(self, coordinates: Sequence, armature: ArrayInput):
        from ._coordinates import AbstractCoordinate

        coordinates = tuple(coordinates)
        for c in coordinates:
            if not isinstance(c, AbstractCoordinate):
                raise TypeError(f"JointArmature takes joint coordinates, got {type(c).__name__}")
        self.coordinates = coordinates
        self.armature = jnp.broadcast_to(jnp.asarray(armature, dtype=float), (len(coordinates),))

    def gradients(self, x: Vector) -> Float[Array, "k p"]:
        """The joint gradients `grad q_j(x)` as columns."""
        return jnp.stack([c.gradient(x) for c in self.coordinates], axis=1)

    def kinetic_energy(self, x: Vector, xd: Vector) -> Scalar:
        """`1/2 sum_j a_j qd_j^2`."""
        rates = self.gradients(x).T @ xd
        return 0.5 * jnp.sum(self.armature * rates**2)

    def bias(self, x: Vector, xd: Vector) -> Vector:
        """The velocity-product force `-sum_j a_j grad q_j (xd^T D2q_j xd)`."""
        grads = self.gradients(x)
        curv = jnp.stack(
            [
                jax.jvp(lambda y, c=c: jax.jvp(c, (y,), (xd,))[1], (x,), (xd,))[1]
                for c in self.coordinates
            ]
        )
        return -grads @ (self.armature * curv)
