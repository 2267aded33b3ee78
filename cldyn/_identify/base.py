"""The interface of the effect library: what a candidate effect is and what each effect provides.

An effect is a force linear in its parameters, `F = sum_c theta_c phi_c(x, xd, xdd, u)`. Each final
`AbstractEffect` (one per file in this package) says where it can act (its candidates), the Cartesian
force of each of its columns per unit parameter, the cldyn term it adds to a model, its parameters in
MuJoCo's meaning, and how to read them back from a refitted model. The rest of identify never asks
which effect it is holding.
"""

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._coordinates import AbstractCoordinate
from .._custom_types import Vector
from .._dissipation import AbstractDissipation, DissipationSum
from .._potential import AbstractPotential, Gravity, Sum
from .._system import ConstrainedLagrangian

_GRAVITY = 9.81


def gravity_of(model: ConstrainedLagrangian) -> float:
    """The gravitational acceleration of the model's `Gravity` term (9.81 without one)."""
    for term in potential_terms(model):
        if isinstance(term, Gravity):
            return float(term.g)
    return _GRAVITY


class Context(eqx.Module):
    """What effects act through: the nominal model, its joint coordinates and the names for reports.

    **Arguments:**

    - `model`: the nominal `ConstrainedLagrangian` (its input matrix gives the actuator forces).
    - `coordinates`: the joint coordinates `q_j(x)`, in the order of `joint_names`.
    - `joint_names`, `actuator_names`, `keypoint_names`: names for candidates and reports.
    """

    model: ConstrainedLagrangian
    coordinates: tuple[AbstractCoordinate, ...]
    joint_names: tuple[str, ...] = eqx.field(static=True, default=())
    actuator_names: tuple[str, ...] = eqx.field(static=True, default=())
    keypoint_names: tuple[str, ...] = eqx.field(static=True, default=())

    @property
    def gravity(self) -> float:
        """The nominal model's gravitational acceleration."""
        return gravity_of(self.model)


class Point(eqx.Module):
    """One sample of the smoothed data: positions, velocities, accelerations, controls, and the joint
    coordinates unwrapped along the run (a spring's angle may pass `pi`)."""

    x: Vector
    xd: Vector
    xdd: Vector
    u: Float[Array, " l"]
    q: Float[Array, " m"]


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One effect at one place: a group of regression columns.

    **Fields:**

    - `effect`: the `AbstractEffect`.
    - `where`: the joint, actuator or keypoint name.
    - `index`: the joint, actuator column or keypoint index.
    - `kind`: a variant within the effect (`"linear"` or `"quadratic"` drag), else empty.
    - `acts_on`: what `where` names: `"joint"`, `"actuator"` or `"keypoint"` (a joint and an
      actuator may share a name); what the data must show for the candidate to be examined.
    """

    effect: "AbstractEffect"
    where: str
    index: int
    kind: str = ""
    acts_on: str = "joint"

    @property
    def name(self) -> str:
        """The effect's name in reports, e.g. `"joint_damping"`."""
        return self.effect.name

    @property
    def columns(self) -> tuple[str, ...]:
        """The names of its regression coefficients."""
        return self.effect.columns

    @property
    def signs(self) -> tuple[int, ...]:
        """Per column, `+1` if physics demands a non-negative value, `0` if free."""
        return self.effect.signs

    @property
    def label(self) -> str:
        """A short name such as `joint_damping[shoulder]`."""
        kind = f"/{self.kind}" if self.kind else ""
        return f"{self.name}{kind}[{self.where}]"

    def parameters(self, theta: np.ndarray) -> dict[str, float]:
        """Its parameters in MuJoCo's meaning and SI units from its coefficients; `"value"` is the
        headline figure."""
        return self.effect.parameters(self, np.asarray(theta, dtype=float))


class AbstractEffect(eqx.Module):
    """A physical effect that a model may lack, as a force linear in its parameters.

    Final effects set the class variables `name` (the name in reports), `columns` (the names of the
    coefficients of one candidate) and `signs` (`+1` for a coefficient that physics makes
    non-negative, `0` for a free one), and implement the five methods below. Adding an effect to
    identify means writing one such class.

    !!! example

        ```python
        class JointDamping(AbstractEffect):
            name: ClassVar[str] = "joint_damping"

            def candidates(self, context):
                return joint_candidates(self, context)

            def force(self, candidate, context, point):
                grad, rate = joint_rate(context, candidate, point)
                return (-grad * rate)[:, None]
            ...
        ```
    """

    name: eqx.AbstractClassVar[str]
    columns: ClassVar[tuple[str, ...]] = ("value",)
    signs: ClassVar[tuple[int, ...]] = (1,)

    @abc.abstractmethod
    def candidates(self, context: Context) -> tuple[Candidate, ...]:
        """Every place this effect could act: one `Candidate` per joint, actuator or keypoint."""

    @abc.abstractmethod
    def force(self, candidate: Candidate, context: Context, point: Point) -> Float[Array, "k c"]:
        """The Cartesian force of each column per unit coefficient at one sample, shape
        `(k, len(columns))`."""

    @abc.abstractmethod
    def parameters(self, candidate: Candidate, theta: np.ndarray) -> dict[str, float]:
        """The effect's parameters in MuJoCo's meaning (SI units) from its coefficients `theta`;
        the entry `"value"` is the figure reported and tested."""

    @abc.abstractmethod
    def augment(
        self, model: ConstrainedLagrangian, candidate: Candidate, theta: np.ndarray, context: Context
    ) -> ConstrainedLagrangian:
        """The model with this effect added as a cldyn term, at the coefficients `theta`."""

    @abc.abstractmethod
    def refitted(
        self, model: ConstrainedLagrangian, candidate: Candidate, context: Context
    ) -> dict[str, float] | None:
        """The effect's parameters as the refitted `model` holds them (the term `augment` added), or
        `None` where the refit does not change them."""

    @abc.abstractmethod
    def unrepresentable(
        self, candidate: Candidate, parameters: dict[str, float], q: np.ndarray
    ) -> np.ndarray | None:
        """Where the term `augment` adds cannot follow the effect, given its `parameters` and the
        unwrapped joint coordinates `q` `(..., m)` of the data: a boolean mask `q.shape[:-1]` (a hinge
        spring wound more than half a turn from its rest, which a function of the keypoints cannot
        tell from one wound less), or `None` where it follows it everywhere. identify leaves those
        samples out of the refit and the rollouts."""


# -- helpers shared by the effects ---------------------------------------------------------------


def everywhere(candidate: Candidate, parameters: dict[str, float], q: np.ndarray) -> None:
    """`unrepresentable` of an effect whose term follows it everywhere."""
    return None


def value(theta: np.ndarray) -> dict[str, float]:
    """The parameters of a one-coefficient effect whose coefficient is its value."""
    return {"value": float(theta[0])}


def joint_candidates(effect: AbstractEffect, context: Context) -> tuple[Candidate, ...]:
    """One candidate per joint coordinate."""
    return tuple(Candidate(effect, name, j) for j, name in enumerate(context.joint_names))


def joint_rate(context: Context, candidate: Candidate, point: Point) -> tuple[Vector, Array]:
    """`(grad q_j(x), qd_j)` of the candidate's joint."""
    grad = context.coordinates[candidate.index].gradient(point.x)
    return grad, jnp.dot(grad, point.xd)


def joint_acceleration(coordinate: AbstractCoordinate, point: Point) -> Array:
    """`qdd = grad q . xdd + xd^T D2q xd`, the curvature by two JVPs (no Hessian)."""
    rate = lambda y: jax.jvp(coordinate, (y,), (point.xd,))[1]
    curvature = jax.jvp(rate, (point.x,), (point.xd,))[1]
    return jnp.dot(coordinate.gradient(point.x), point.xdd) + curvature


def keypoint_force(context: Context, candidate: Candidate, force: Array) -> Vector:
    """A force `(2,)` on the candidate's keypoint as a keypoint-coordinate vector `(k,)`."""
    index = candidate.index
    return jnp.zeros(context.model.size, dtype=force.dtype).at[2 * index : 2 * index + 2].set(force)


def same(a, b) -> bool:
    """Whether two modules are the same (type and every leaf)."""
    return type(a) is type(b) and bool(eqx.tree_equal(a, b))


def potential_terms(model: ConstrainedLagrangian) -> tuple[AbstractPotential, ...]:
    """The model's potential as a tuple of terms (empty without one)."""
    if model.potential is None:
        return ()
    return model.potential.terms if isinstance(model.potential, Sum) else (model.potential,)


def dissipation_terms(model: ConstrainedLagrangian) -> tuple[AbstractDissipation, ...]:
    """The model's dissipation as a tuple of terms (empty without one)."""
    if model.dissipation is None:
        return ()
    return model.dissipation.terms if isinstance(model.dissipation, DissipationSum) else (model.dissipation,)


def add_potential(model: ConstrainedLagrangian, term: AbstractPotential) -> ConstrainedLagrangian:
    """The model with `term` added to its potential."""
    potential = term if model.potential is None else model.potential + term
    return eqx.tree_at(lambda s: s.potential, model, potential, is_leaf=lambda v: v is None)


def add_dissipation(model: ConstrainedLagrangian, term: AbstractDissipation) -> ConstrainedLagrangian:
    """The model with `term` added to its dissipation (always a `DissipationSum`)."""
    dissipation = term if model.dissipation is None else model.dissipation + term
    if not isinstance(dissipation, DissipationSum):
        dissipation = DissipationSum([dissipation])
    return eqx.tree_at(lambda s: s.dissipation, model, dissipation, is_leaf=lambda v: v is None)


def joint_term_value(terms, kind: type, field: str, coordinate: AbstractCoordinate) -> float | None:
    """The value of `field` in the last term of type `kind` that acts on `coordinate` alone first
    (what `augment` adds), or `None`."""
    found = None
    for term in terms:
        if isinstance(term, kind) and same(term.coordinates[0], coordinate):
            found = float(getattr(term, field)[0])
    return found
