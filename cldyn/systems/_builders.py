from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .._constraint import Anchor, Distance, FixedCoordinate, Stack
from .._coordinates import HingeAngle, JointMap, SliderPosition, wrap_angle
from .._custom_types import ArrayInput
from .._input import JointInput
from .._mass import (
    ConstantMass,
    pivot_body_gravity,
    pivot_body_mass,
    rigid_body_gravity,
    rigid_body_mass,
)
from .._potential import Gravity
from .._system import ConstrainedLagrangian


def _per_link(name: str, value, n: int) -> np.ndarray:
    array = np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy()
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got {array}")
    return array


def _actuator_indices(actuators, num_joints: int) -> tuple[int, ...]:
    if actuators == "all":
        return tuple(range(num_joints))
    if actuators is None:
        return ()
    indices = tuple(int(a) for a in actuators)
    for a in indices:
        if not 0 <= a < num_joints:
            raise ValueError(f"actuator index {a} out of range for {num_joints} joints")
    if len(set(indices)) != len(indices):
        raise ValueError(f"actuators repeat a joint: {indices}")
    return indices


def _direction(theta):
    return jnp.stack([jnp.sin(theta), -jnp.cos(theta)], axis=-1)


def _angle_from_down(v):
    return jnp.arctan2(v[..., 0], -v[..., 1])


def _link_geometry(length, com, offset):
    """Two body points (joint, far end) and the centre of mass in the link's own frame."""
    return np.array([[0.0, 0.0], [length, 0.0]]), np.array([com, offset])


def chain(
    n: int,
    *,
    masses: ArrayInput = 1.0,
    lengths: ArrayInput = 1.0,
    coms: ArrayInput | None = None,
    com_offsets: ArrayInput = 0.0,
    inertias: ArrayInput = 0.0,
    gravity: float = 9.81,
    actuators: Sequence[int] | str | None = "all",
    gears: ArrayInput = 1.0,
) -> tuple[ConstrainedLagrangian, JointMap]:
    """A planar chain of `n` rigid links hanging from a fixed pivot at the origin.

    Keypoint `i` is the far end of link `i`. Link 0 pivots about the origin (an `Anchor`); link `i`
    is carried by keypoints `i - 1` and `i` (a `Distance`). The masses are the exact rigid-body blocks,
    so the dynamics equal those of the generalised-coordinate chain.

    **Arguments:**

    - `n`: number of links.
    - `masses`, `lengths`: per link (scalars broadcast).
    - `coms`: distance of each link's centre of mass from its joint, along the link; at the far end
      (a point mass, as in KeyCLD) by default.
    - `com_offsets`: offset of each centre of mass perpendicular to the link (counter-clockwise side).
    - `inertias`: rotational inertia of each link about its centre of mass.
    - `gravity`: gravitational acceleration along `-y`.
    - `actuators`: indices of the joints with a motor, `"all"`, or `None`.
    - `gears`: gear of each motor (scalar broadcasts).

    **Returns:** `(system, joints)`; the joint coordinates are the absolute angle of link 0 from
    straight down and the relative angle of each following link to its predecessor.

    !!! example

        ```python
        system, joints = cldyn.systems.chain(3, lengths=[1.0, 0.8, 0.6])
        x, xd = joints.to_keypoints(jnp.array([0.1, 0.2, 0.3]), jnp.zeros(3))
        ```
    """
    if n < 1:
        raise ValueError(f"a chain needs at least one link, got n={n}")
    masses = _per_link("masses", masses, n)
    lengths = _per_link("lengths", lengths, n)
    coms = lengths.copy() if coms is None else _per_link("coms", coms, n)
    com_offsets = _per_link("com_offsets", com_offsets, n)
    inertias = _per_link("inertias", inertias, n)
    if np.any(lengths <= 0) or np.any(masses < 0) or np.any(inertias < 0):
        raise ValueError("lengths must be positive; masses and inertias non-negative")

    blocks, weights = [], jnp.zeros(2 * n)
    for i in range(n):
        points, com = _link_geometry(lengths[i], coms[i], com_offsets[i])
        if i == 0:
            blocks.append(((0,), pivot_body_mass(masses[0], inertias[0], com, *points)))
            weights = weights.at[0:2].add(pivot_body_gravity(masses[0], com, *points))
        else:
            blocks.append(((i - 1, i), rigid_body_mass(masses[i], inertias[i], com, points)))
            weights = weights.at[2 * i - 2 : 2 * i + 2].add(
                rigid_body_gravity(masses[i], com, points)
            )
    mass = ConstantMass.from_blocks(blocks, n)
    constraint = Stack([Anchor(0)] + [Distance(i - 1, i) for i in range(1, n)])

    def hinge(i):
        if i == 0:
            return HingeAngle(child=(None, 0))
        return HingeAngle(child=(i - 1, i), parent=(None if i == 1 else i - 2, i - 1))

    indices = _actuator_indices(actuators, n)
    input_matrix = None
    if indices:
        gears = _per_link("gears", gears, len(indices))
        input_matrix = JointInput([hinge(i) for i in indices], gears)

    def forward(q):
        theta = jnp.cumsum(q)
        return jnp.cumsum(lengths[:, None] * _direction(theta), axis=0).reshape(-1)

    def inverse(x):
        points = x.reshape(n, 2)
        segments = jnp.diff(jnp.concatenate([jnp.zeros((1, 2)), points]), axis=0)
        theta = _angle_from_down(segments)
        return wrap_angle(jnp.concatenate([theta[:1], jnp.diff(theta)]))

    system = ConstrainedLagrangian(
        mass=mass,
        potential=Gravity(weights, gravity),
        constraint=constraint,
        input_matrix=input_matrix,
    )
    names = tuple(["shoulder"] + [f"joint{i}" for i in range(1, n)]) if n > 1 else ("hinge",)
    return system, JointMap(forward, inverse, names)


def pendulum(
    *,
    mass: float = 1.0,
    length: float = 1.0,
    com: float | None = None,
    com_offset: float = 0.0,
    inertia: float = 0.0,
    gravity: float = 9.81,
    actuated: bool = True,
    gear: float = 1.0,
) -> tuple[ConstrainedLagrangian, JointMap]:
    """A pendulum: one keypoint at the end of a rigid body pivoting about the origin.

    KeyCLD's pendulum (appendix A.6): one keypoint and an `Anchor` constraint. By default a point mass
    at the end of a massless rod.

    **Arguments:**

    - `mass`, `length`: of the body.
    - `com`: distance of the centre of mass from the pivot along the rod; `length` by default.
    - `com_offset`: perpendicular offset of the centre of mass.
    - `inertia`: rotational inertia about the centre of mass.
    - `gravity`: gravitational acceleration.
    - `actuated`: whether a motor drives the hinge.
    - `gear`: the motor's gear.

    **Returns:** `(system, joints)` with the single joint angle measured from straight down.
    """
    return chain(
        1,
        masses=mass,
        lengths=length,
        coms=com,
        com_offsets=com_offset,
        inertias=inertia,
        gravity=gravity,
        actuators="all" if actuated else None,
        gears=gear,
    )


def acrobot(
    *,
    masses: ArrayInput = (1.0, 1.0),
    lengths: ArrayInput = (1.0, 1.0),
    coms: ArrayInput | None = None,
    com_offsets: ArrayInput = 0.0,
    inertias: ArrayInput = 0.0,
    gravity: float = 9.81,
    actuators: Sequence[int] | str | None = (1,),
    gears: ArrayInput = 1.0,
) -> tuple[ConstrainedLagrangian, JointMap]:
    """An acrobot: a two-link chain, actuated at the elbow by default.

    KeyCLD uses a fully actuated acrobot: pass `actuators="all"`. Arguments as in `chain`.

    **Returns:** `(system, joints)` with joints `(shoulder, elbow)`.
    """
    system, joints = chain(
        2,
        masses=masses,
        lengths=lengths,
        coms=coms,
        com_offsets=com_offsets,
        inertias=inertias,
        gravity=gravity,
        actuators=actuators,
        gears=gears,
    )
    return system, JointMap(joints.forward, joints.inverse, ("shoulder", "elbow"))


def cartpole(
    *,
    cart_mass: float = 1.0,
    pole_mass: float = 0.1,
    length: float = 1.0,
    com: float | None = None,
    com_offset: float = 0.0,
    pole_inertia: float = 0.0,
    gravity: float = 9.81,
    actuators: Sequence[int] | str | None = (0,),
    gears: ArrayInput = 1.0,
) -> tuple[ConstrainedLagrangian, JointMap]:
    """A cart on a horizontal rail with a pole hinged on it.

    Two keypoints as in KeyCLD (appendix A.6): the cart (`FixedCoordinate`: its height is constant)
    and the end of the pole (`Distance` to the cart).

    **Arguments:**

    - `cart_mass`: mass of the cart.
    - `pole_mass`, `length`: of the pole (hinge to keypoint).
    - `com`, `com_offset`, `pole_inertia`: the pole's centre of mass and inertia, as in `pendulum`.
    - `gravity`: gravitational acceleration.
    - `actuators`: joint indices with a motor: 0 is the cart force, 1 the hinge torque.
    - `gears`: gear of each motor.

    **Returns:** `(system, joints)` with joints `(cart, pole)`: the cart position and the pole
    angle from straight down.
    """
    if cart_mass <= 0:
        raise ValueError(f"cart_mass must be positive, got {cart_mass}")
    com = length if com is None else com
    points, com_point = _link_geometry(length, com, com_offset)
    blocks = [
        ((0,), cart_mass * jnp.eye(2)),
        ((0, 1), rigid_body_mass(pole_mass, pole_inertia, com_point, points)),
    ]
    weights = jnp.zeros(4).at[1].add(cart_mass)
    weights = weights + rigid_body_gravity(pole_mass, com_point, points)
    coordinates = (SliderPosition(0), HingeAngle(child=(0, 1)))
    indices = _actuator_indices(actuators, 2)
    input_matrix = None
    if indices:
        gears = _per_link("gears", gears, len(indices))
        input_matrix = JointInput([coordinates[i] for i in indices], gears)

    def forward(q):
        cart = jnp.stack([q[0], jnp.zeros_like(q[0])])
        return jnp.concatenate([cart, cart + length * _direction(q[1])])

    def inverse(x):
        return jnp.stack([x[0], wrap_angle(_angle_from_down(x[2:4] - x[0:2]))])

    system = ConstrainedLagrangian(
        mass=ConstantMass.from_blocks(blocks, 2),
        potential=Gravity(weights, gravity),
        constraint=Stack([FixedCoordinate(0, axis=1), Distance(0, 1)]),
        input_matrix=input_matrix,
    )
    return system, JointMap(forward, inverse, ("cart", "pole"))


def four_bar(
    *,
    ground: float = 2.0,
    crank: float = 0.5,
    coupler: float = 2.0,
    rocker: float = 1.5,
    masses: ArrayInput = (1.0, 1.0, 1.0),
    gravity: float = 9.81,
    actuated: bool = True,
) -> tuple[ConstrainedLagrangian, None]:
    """A planar four-bar linkage: a closed kinematic loop.

    Fixed pivots `A = (0, 0)` and `D = (ground, 0)`; keypoint 0 is the crank end `B`, keypoint 1 the
    coupler-rocker joint `C`. Constraints: `|B - A|`, `|C - B|`, `|C - D|` constant. Each link is a
    uniform rod (centre of mass at its middle, inertia `m L^2 / 12`). The default proportions make a
    Grashof crank-rocker. A closed loop has no global minimal coordinates, so no `JointMap` is
    returned; make states consistent with `cldyn.project_state`.

    **Arguments:**

    - `ground`, `crank`, `coupler`, `rocker`: link lengths.
    - `masses`: masses of crank, coupler and rocker.
    - `gravity`: gravitational acceleration.
    - `actuated`: whether a motor drives the crank.

    **Returns:** `(system, None)`.
    """
    lengths = np.array([crank, coupler, rocker], dtype=float)
    if np.any(lengths <= 0) or ground <= 0:
        raise ValueError("link lengths must be positive")
    masses = _per_link("masses", masses, 3)
    inertias = masses * lengths**2 / 12
    pivot_a, pivot_d = np.zeros(2), np.array([ground, 0.0])
    # A reference configuration only fixes where each centre of mass sits on its link.
    b_ref = pivot_a + np.array([0.0, crank])
    c_ref = _circle_intersection(b_ref, coupler, pivot_d, rocker)
    crank_com = 0.5 * (pivot_a + b_ref)
    coupler_pts = np.stack([b_ref, c_ref])
    rocker_com = 0.5 * (pivot_d + c_ref)
    blocks = [
        ((0,), pivot_body_mass(masses[0], inertias[0], crank_com, pivot_a, b_ref)),
        ((0, 1), rigid_body_mass(masses[1], inertias[1], coupler_pts.mean(0), coupler_pts)),
        ((1,), pivot_body_mass(masses[2], inertias[2], rocker_com, pivot_d, c_ref)),
    ]
    weights = jnp.concatenate(
        [pivot_body_gravity(masses[0], crank_com, pivot_a, b_ref), jnp.zeros(2)]
    )
    weights = weights + rigid_body_gravity(masses[1], coupler_pts.mean(0), coupler_pts)
    weights = weights.at[2:].add(pivot_body_gravity(masses[2], rocker_com, pivot_d, c_ref))
    input_matrix = JointInput([HingeAngle(child=(None, 0))]) if actuated else None
    system = ConstrainedLagrangian(
        mass=ConstantMass.from_blocks(blocks, 2),
        potential=Gravity(weights, gravity),
        constraint=Stack([Anchor(0, pivot_a), Distance(0, 1), Anchor(1, pivot_d)]),
        input_matrix=input_matrix,
    )
    return system, None


def _circle_intersection(c1, r1, c2, r2) -> np.ndarray:
    """The upper intersection of two circles (left of the line from `c1` to `c2`)."""
    d = np.linalg.norm(c2 - c1)
    a = (r1**2 - r2**2 + d**2) / (2 * d)
    h2 = r1**2 - a**2
    if h2 < 0:
        raise ValueError("these four-bar lengths cannot be assembled")
    e = (c2 - c1) / d
    return c1 + a * e + np.sqrt(h2) * np.array([-e[1], e[0]])
