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

    Implementations provide `Phi(x)`, its Jacobian `DPhi(x)` and the curvature term
    `<D2Phi(x), xd> xd`. The built-in constraints use closed forms (several times faster than
    automatic differentiation in the integrator's inner loop); `FromFunction` derives both by
    automatic differentiation of any user function.
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

    @abc.abstractmethod
    def jacobian(self, x: Vector) -> Float[Array, "n k"]:
        """The constraint Jacobian `DPhi(x)`, shape `(n, k)`."""

    @abc.abstractmethod
    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        """The curvature term `<D2Phi(x), xd> xd = d/dt (DPhi(x)) xd` of eq. 6, shape `(n,)`."""

    def velocity(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        """The constraint velocity `d/dt Phi = DPhi(x) xd`."""
        return self.jacobian(x) @ xd


class _AbstractAutodiffConstraint(AbstractConstraint):
    """Derives the Jacobian and the curvature term from `__call__` by automatic differentiation."""

    def jacobian(self, x: Vector) -> Float[Array, "n k"]:
        return jax.jacfwd(self.__call__)(x)

    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        # The JVP along xd of x -> DPhi(x) xd: two forward passes, never the (n, k, k) Hessian.
        tangent = lambda y: jax.jvp(self.__call__, (y,), (xd,))[1]
        return jax.jvp(tangent, (x,), (xd,))[1]


def _row(k: int, dim: int, pieces: tuple[tuple[int, Array], ...], dtype) -> Array:
    """A length-`k` row with the `dim`-vectors `pieces[(keypoint, value)]` placed at their keypoints."""
    row = jnp.zeros(k, dtype=dtype)
    for index, value in pieces:
        row = row.at[dim * index : dim * (index + 1)].add(value)
    return row


def _dot(a: Array, b: Array) -> Array:
    """`a . b` of two short vectors (a keypoint's coordinates), written out as multiply-adds: a
    reduction is a kernel of its own on CPU, while multiply-adds fuse with the work around them."""
    out = a[0] * b[0]
    for i in range(1, a.shape[0]):
        out = out + a[i] * b[i]
    return out


def _distance_terms(delta: Array, rate: Array) -> tuple[Array, Array, Array]:
    """`|d|`, the unit vector `d/|d|` and the curvature `(|dd|^2 - (u . dd)^2) / |d|` of `|d|`."""
    length = jnp.sqrt(_dot(delta, delta))
    unit = delta / length
    along = _dot(unit, rate)
    return length, unit, (_dot(rate, rate) - along**2) / length


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


def _float_array(value) -> Array:
    return jnp.asarray(value, dtype=float)


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

    def _delta(self, v: Vector) -> Array:
        return v[_point_slice(self.first, self.dim)] - v[_point_slice(self.second, self.dim)]

    def _segment(self) -> tuple[int, int | None, tuple[float, ...]]:
        return self.first, self.second, (0.0,) * self.dim

    def __call__(self, x: Vector) -> Float[Array, " 1"]:
        return jnp.sqrt(_dot(self._delta(x), self._delta(x)))[None]

    def jacobian(self, x: Vector) -> Float[Array, "1 k"]:
        _, unit, _ = _distance_terms(self._delta(x), self._delta(x))
        return _row(x.shape[0], self.dim, ((self.first, unit), (self.second, -unit)), x.dtype)[None]

    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " 1"]:
        return _distance_terms(self._delta(x), self._delta(xd))[2][None]


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

    def _delta(self, x: Vector) -> Array:
        return x[_point_slice(self.keypoint, self.dim)] - jnp.asarray(self.point, dtype=x.dtype)

    def _segment(self) -> tuple[int, int | None, tuple[float, ...]]:
        return self.keypoint, None, self.point

    def __call__(self, x: Vector) -> Float[Array, " 1"]:
        return jnp.sqrt(_dot(self._delta(x), self._delta(x)))[None]

    def jacobian(self, x: Vector) -> Float[Array, "1 k"]:
        _, unit, _ = _distance_terms(self._delta(x), self._delta(x))
        return _row(x.shape[0], self.dim, ((self.keypoint, unit),), x.dtype)[None]

    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " 1"]:
        rate = xd[_point_slice(self.keypoint, self.dim)]
        return _distance_terms(self._delta(x), rate)[2][None]


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

    def jacobian(self, x: Vector) -> Float[Array, "1 k"]:
        return jnp.zeros((1, x.shape[0]), dtype=x.dtype).at[0, self.dim * self.keypoint + self.axis].set(1)

    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " 1"]:
        return jnp.zeros(1, dtype=x.dtype)


class LinearConstraint(AbstractConstraint):
    """Linear constraints on the keypoints: `Phi(x) = rows @ x`.

    A keypoint on a straight rail at any angle (one row, the rail's normal on that keypoint's
    coordinates), or keypoints tied to a body that does not turn. Their Jacobian is `rows` and their
    curvature term is zero. `FixedCoordinate` is the one-row case of a rail along a coordinate axis.

    **Arguments:**

    - `rows`: the constraints' coefficients, shape `(n, k)` for `k` keypoint coordinates; finite, no
      row zero. An array (scenes that differ only in numbers share one compiled program), but no
      parameter: no gradient reaches it, so training a model leaves its constraints as they are.

    !!! example

        ```python
        # the cart (keypoint 0) on a rail inclined by 30 degrees, a pole (keypoint 1) on the cart
        normal = [-np.sin(np.pi / 6), np.cos(np.pi / 6)]
        constraint = cldyn.Stack([cldyn.LinearConstraint([[*normal, 0.0, 0.0]]), cldyn.Distance(0, 1)])
        ```
    """

    rows: Float[Array, "n k"] = eqx.field(converter=_float_array)

    def __check_init__(self):
        if self.rows.ndim != 2 or self.rows.shape[0] == 0:
            raise ValueError(f"LinearConstraint: rows must have shape (n, k), n >= 1; got {self.rows.shape}")
        if isinstance(self.rows, jax.core.Tracer):
            return  # built under a transformation (as a model's shape is): checked where built concretely
        rows = np.asarray(self.rows)
        if not np.all(np.isfinite(rows)) or not np.all(np.any(rows != 0, axis=1)):
            raise ValueError("LinearConstraint: every row must be finite and not all zero")

    @property
    def num_constraints(self) -> int:
        return self.rows.shape[0]

    def _rows(self, x: Vector) -> Array:
        if self.rows.shape[1] != x.shape[-1]:
            raise ValueError(
                f"LinearConstraint: rows are for {self.rows.shape[1]} coordinates, x has {x.shape[-1]}"
            )
        return jax.lax.stop_gradient(self.rows.astype(x.dtype))  # geometry, not a parameter

    def __call__(self, x: Vector) -> Float[Array, " n"]:
        return self._rows(x) @ x

    def jacobian(self, x: Vector) -> Float[Array, "n k"]:
        return self._rows(x)

    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        return jnp.zeros(self.rows.shape[0], dtype=x.dtype)


class AffineMap(eqx.Module):
    """`y(x) = matrix @ x + const`: a planar point or direction affine in the keypoints. Geometry read
    from a scene, not a parameter: no gradient reaches `matrix` or `const`."""

    matrix: Float[Array, "2 k"]
    const: Float[Array, " 2"]

    def __call__(self, x: Vector) -> Float[Array, " 2"]:
        matrix, const = jax.lax.stop_gradient((self.matrix.astype(x.dtype), self.const.astype(x.dtype)))
        return matrix @ x + const


class NormConstraint(_AbstractAutodiffConstraint):
    """`|d(x)| = const` for an affine `d`: a keypoint at a fixed distance from a hinge anchor that is no
    keypoint itself."""

    difference: AffineMap

    @property
    def num_constraints(self) -> int:
        return 1

    def __call__(self, x: Vector) -> Float[Array, " 1"]:
        return jnp.sqrt(jnp.sum(self.difference(x) ** 2))[None]


class BilinearConstraint(_AbstractAutodiffConstraint):
    """`d(x) . n(x) = const`: a keypoint slides along a line fixed in a rotating parent."""

    displacement: AffineMap
    normal: AffineMap

    @property
    def num_constraints(self) -> int:
        return 1

    def __call__(self, x: Vector) -> Float[Array, " 1"]:
        return jnp.dot(self.displacement(x), self.normal(x))[None]


class _Segments:
    """The `Distance` and `Anchor` rows of a `Stack`, evaluated together in one vectorised pass.

    Row `r` is the length of the segment whose coordinate `d` is `select[d, r] @ x - offset[d, r]`
    (`select[d]` picks keypoint `first` minus keypoint `second`, or a fixed point's offset). One
    reciprocal square root of all squared lengths gives the values, the Jacobian rows and the
    curvature terms: in the integrator's inner loop every square root is a kernel of its own on CPU
    (XLA neither duplicates nor merges them), so `m` segments evaluated apart cost `m` times the
    kernels. The products with `select` are multiply-adds over the coordinates that the segments
    use, which fuse with the work around them; gathers or stacked slices of `x` were measured slower
    for one trajectory.
    """

    def __init__(self, select: np.ndarray, offset: np.ndarray):
        self.select = select  # (dim, m, k), entries 0, +1, -1
        self.offset = offset  # (dim, m)

    def _deltas(self, v: Vector, offset: bool) -> list[Array]:
        out = []
        for d in range(self.select.shape[0]):
            # multiply-adds over the coordinates that some segment uses (the others' columns are 0)
            columns = np.flatnonzero(np.any(self.select[d] != 0, axis=0))
            delta = sum(jnp.asarray(self.select[d][:, j], dtype=v.dtype) * v[int(j)] for j in columns)
            out.append(delta - jnp.asarray(self.offset[d], dtype=v.dtype) if offset else delta)
        return out

    def _units(self, x: Vector) -> tuple[Array, Array, list[Array]]:
        """The squared lengths, their inverse square roots, and the unit vectors by coordinate."""
        deltas = self._deltas(x, offset=True)
        squared = sum(delta**2 for delta in deltas)
        # the value, the Jacobian and the curvature all from the one reciprocal square root
        inverse = 1 / jnp.sqrt(squared)
        return squared, inverse, [delta * inverse for delta in deltas]

    def __call__(self, x: Vector) -> Array:
        squared, inverse, _ = self._units(x)
        return squared * inverse

    def jacobian(self, x: Vector) -> Array:
        _, _, units = self._units(x)
        return sum(unit[:, None] * jnp.asarray(self.select[d], dtype=x.dtype) for d, unit in enumerate(units))

    def curvature(self, x: Vector, xd: Vector) -> Array:
        _, inverse, units = self._units(x)
        rates = self._deltas(xd, offset=False)
        along = sum(unit * rate for unit, rate in zip(units, rates))
        return (sum(rate**2 for rate in rates) - along**2) * inverse


def _segments(constraints: tuple[AbstractConstraint, ...], k: int) -> _Segments | None:
    """The `Distance` and `Anchor` members of `constraints` as `_Segments`, when there are at least
    two of them (of one keypoint dimension) and their keypoints lie within `k` coordinates."""
    members = [c for c in constraints if isinstance(c, Distance | Anchor)]
    if len(members) < 2 or len({c.dim for c in members}) != 1:
        return None
    dim = members[0].dim
    select = np.zeros((dim, len(members), k))
    offset = np.zeros((dim, len(members)))
    for row, member in enumerate(members):
        first, second, point = member._segment()
        if dim * (max(first, second or 0) + 1) > k:
            return None  # out of range: the members' own code reports it
        for d in range(dim):
            select[d, row, dim * first + d] = 1.0
            if second is not None:
                select[d, row, dim * second + d] = -1.0
            offset[d, row] = point[d]
    return _Segments(select, offset)


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

    def _rows(self, x: Vector, each, together) -> list[Array]:
        """The members' rows in order: `each(member)` for a member on its own, rows of
        `together(segments)` for the `Distance` and `Anchor` members evaluated together."""
        segments = _segments(self.constraints, x.shape[0])
        joint = None if segments is None else together(segments)
        rows, row = [], 0
        for c in self.constraints:
            if segments is not None and isinstance(c, Distance | Anchor):
                rows.append(joint[row : row + 1])
                row += 1
            else:
                rows.append(each(c))
        return rows

    def __call__(self, x: Vector) -> Float[Array, " n"]:
        if not self.constraints:
            return jnp.zeros(0, dtype=x.dtype)
        return jnp.concatenate(self._rows(x, lambda c: c(x), lambda s: s(x)))

    def jacobian(self, x: Vector) -> Float[Array, "n k"]:
        if not self.constraints:
            return jnp.zeros((0, x.shape[0]), dtype=x.dtype)
        return jnp.concatenate(self._rows(x, lambda c: c.jacobian(x), lambda s: s.jacobian(x)), axis=0)

    def curvature(self, x: Vector, xd: Vector) -> Float[Array, " n"]:
        if not self.constraints:
            return jnp.zeros(0, dtype=x.dtype)
        return jnp.concatenate(self._rows(x, lambda c: c.curvature(x, xd), lambda s: s.curvature(x, xd)))


class FromFunction(_AbstractAutodiffConstraint):
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
